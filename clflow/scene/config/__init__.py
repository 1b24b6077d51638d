"""Scene configuration files (YAML or JSON) for `clflow optimize` and `clflow simulate CONFIG`.

Every key is checked: unknown keys (typos), wrong types and out-of-range values raise an
:class:`~clflow.errors.InputError` that names the file and the dotted key, e.g.
``scene.yaml: simulation.frames: must be an integer >= 1, got -3``. Paths are relative to
the config file. Lengths in the ``simulation``/``forces``/``boundaries`` sections are metres
in the simulation frame (+y up), and so is ``object.velocity`` (m/s); ``object.select`` is in
scene units of the splat file. A scene of several objects lists them under ``objects`` (each
its select, fill, velocity and material, and a name); either form is read into
``SceneConfig.objects``, a tuple of :class:`SceneObject`.

A complete example with every default spelled out: ``docs/scene_config.md``.

The package's modules: ``keys`` (a key's declaration: kind, unit, default, range, meaning),
``settings`` and ``optimize_settings`` (the types, section by section, their fields declaring
their keys), ``schema`` (every section's keys), ``reader`` (a key's type and range checked,
errors naming file and key), ``parse`` with ``parse_objects`` and ``parse_optimize`` (a parsed
config checked into a SceneConfig), ``files`` (strict YAML/JSON, ``--set`` overrides,
load_config) and ``doc`` (the key tables of docs/scene_config.md, written from the schema).
"""

from clflow.scene.config import optimize_settings, settings
from clflow.scene.config.files import load_config
from clflow.scene.config.optimize_settings import *  # noqa: F403  (optimize_settings.__all__)
from clflow.scene.config.parse import parse_config
from clflow.scene.config.settings import *  # noqa: F403  (the config's types and names: settings.__all__)

__all__ = [*settings.__all__, *optimize_settings.__all__, "load_config", "parse_config"]
