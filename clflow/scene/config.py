"""Scene configuration files (YAML or JSON) for `clflow optimize` and `clflow simulate CONFIG`.

Every key is checked: unknown keys (typos), wrong types and out-of-range values raise an
:class:`~clflow.errors.InputError` that names the file and the dotted key, e.g.
``scene.yaml: simulation.frames: must be an integer >= 1, got -3``. Paths are relative to
the config file. Lengths in the ``simulation``/``forces``/``boundaries`` sections are metres
in the simulation frame (+y up), and so is ``object.velocity`` (m/s); ``object.select`` is in
scene units of the splat file.

A complete example with every default spelled out: ``docs/scene_config.md``.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

from clflow.errors import InputError
from clflow.flow.optical_flow import (
    BIAS_CORRECTIONS,
    CONFIDENCES,
    DEFAULT_BIAS_CORRECTION,
    DEFAULT_CONFIDENCE,
    DEFAULT_PRESET,
    DIS_PRESETS,
)
from clflow.materials import DENSITY, get_material, validate_params
from clflow.mpm.constants import COLLIDER_MODES, ELASTIC_MODELS, SAND_MODELS
from clflow.regions import Region

UP_AXES = ("+x", "-x", "+y", "-y", "+z", "-z")
FLOW_METHODS = ("dis", "farneback")
FLOW_LOSSES = ("l2", "charbonnier")
MATERIAL_MODELS = {"elastic": ELASTIC_MODELS, "sand": SAND_MODELS}  # material.model options
VELOCITY = "velocity"  # the name of the object's initial velocity in optimize.parameters, evaluation.ground_truth
VELOCITY_COMPONENTS = ("velocity_x", "velocity_y", "velocity_z")  # its components: m/s, scene axes


_DEFAULT = object()


class _Reader:
    """Walks a parsed config with the dotted path of each key for error messages."""

    def __init__(self, source: str, base: Path):
        self.source = source
        self.base = base

    def fail(self, path: str, message: str) -> InputError:
        return InputError(f"{self.source}: {path}: {message}" if path else f"{self.source}: {message}")

    def section(self, data: Any, path: str, known: tuple[str, ...]) -> dict:
        data = self.mapping(data, path)
        unknown = [k for k in data if k not in known]
        if unknown:
            raise self.fail(
                f"{path}.{unknown[0]}" if path else str(unknown[0]), f"unknown key; known keys here: {', '.join(known)}"
            )
        return data

    def mapping(self, data: Any, path: str) -> dict:
        """A mapping whose keys are checked elsewhere."""
        if data is None:
            return {}
        if not isinstance(data, dict):
            raise self.fail(path, f"must be a mapping of keys to values, got {type(data).__name__}")
        return data

    def _get(self, data: dict, key: str, path: str, default: Any) -> tuple[str, Any]:
        """(dotted key, value), value _DEFAULT when absent and a default exists."""
        where = f"{path}.{key}" if path else key
        if key not in data or data[key] is None:
            if default is None:
                raise self.fail(where, "is required")
            return where, _DEFAULT
        return where, data[key]

    def number(
        self,
        data: dict,
        key: str,
        path: str,
        default: float | None = None,
        *,
        low: float | None = None,
        high: float | None = None,
        strict_low: bool = False,
    ) -> float:
        where, value = self._get(data, key, path, default)
        if value is _DEFAULT:
            return default
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(where, f"must be a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise self.fail(where, f"must be finite, got {value}")
        if low is not None and (value < low or (strict_low and value == low)):
            raise self.fail(where, f"must be {'>' if strict_low else '>='} {low:g}, got {value:g}")
        if high is not None and value > high:
            raise self.fail(where, f"must be <= {high:g}, got {value:g}")
        return value

    def integer(self, data: dict, key: str, path: str, default: int | None = None, *, low: int = 0) -> int:
        where, value = self._get(data, key, path, default)
        if value is _DEFAULT:
            return default
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise self.fail(where, f"must be an integer >= {low}, got {value!r}")
        return value

    def vec3(self, data: dict, key: str, path: str, default: tuple | None = None) -> tuple[float, float, float]:
        where, value = self._get(data, key, path, default)
        if value is _DEFAULT:
            return default
        if (
            not isinstance(value, (list, tuple))
            or len(value) != 3
            or not all(isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in value)
        ):
            raise self.fail(where, f"must be a list of 3 finite numbers, got {value!r}")
        return tuple(float(c) for c in value)

    def choice(self, data: dict, key: str, path: str, options: tuple[str, ...], default: str | None = None) -> str:
        where = f"{path}.{key}" if path else key
        value = data.get(key)
        if value is None:
            value = default
        if value is None:
            raise self.fail(where, "is required")
        if value not in options:
            raise self.fail(where, f"must be one of {', '.join(options)}, got {value!r}")
        return value

    def file(self, data: dict, key: str, path: str, required: bool = True, folder_ok: bool = False) -> Path | None:
        where = f"{path}.{key}" if path else key
        value = data.get(key)
        if value is None:
            if required:
                raise self.fail(where, "is required (a file path, relative to the config file)")
            return None
        if not isinstance(value, str) or not value:
            raise self.fail(where, f"must be a file path, got {value!r}")
        resolved = (self.base / value).resolve()
        if not (resolved.is_file() or (folder_ok and resolved.is_dir())):
            raise self.fail(where, f"{'file or folder' if folder_ok else 'file'} not found: {resolved}")
        return resolved

    def items(self, data: dict, key: str, path: str) -> list:
        value = data.get(key, [])
        if value is None:
            return []
        if not isinstance(value, list):
            raise self.fail(f"{path}.{key}" if path else key, f"must be a list, got {type(value).__name__}")
        return value


# ---------------------------------------------------------------------------------------
# The configuration, section by section.


@dataclass(frozen=True)
class Selection:
    """Which Gaussians form the object: a region in scene units, a mask file (.npy of N
    booleans or of indices), or a PLY of the part (its Gaussian centres matched to the
    scene's within ``tolerance`` scene units; None: 1e-5 of the scene's diagonal plus a
    compressed part's quantisation error)."""

    region: Region | None
    mask: Path | None
    ply: Path | None = None
    tolerance: float | None = None


@dataclass(frozen=True)
class FillSettings:
    enabled: bool = True
    spacing: float | None = None  # m; None: half the grid spacing (8 particles per cell)
    per_axis: int = 1


@dataclass(frozen=True)
class MaterialConfig:
    """``type`` is a registry material, or "query" to ask the material query first."""

    type: str
    parameters: dict[str, float]
    density: float | None  # kg/m^3; None only for "query" without a given density
    model: str | None = None  # elastic: fixed_corotated/neo_hookean; sand: drucker_prager/volume_corrected
    query_image: Path | None = None
    query_result: Path | None = None  # a record of `clflow query`, read instead of asking
    query_prompt: str = ""
    query_backend: str = "offline"


@dataclass(frozen=True)
class ForceStage:
    """A force (N, spread over the region's particles by mass) or an acceleration (m/s^2)
    on a region of particles during [start, end) s."""

    region: Region
    vector: tuple[float, float, float]
    kind: str  # "force" | "acceleration"
    start: float
    end: float


@dataclass(frozen=True)
class Collider:
    point: tuple[float, float, float]
    normal: tuple[float, float, float]
    mode: str
    friction: float
    start: float = 0.0
    end: float = math.inf


DEFAULT_MAX_SUBSTEPS = 2000  # substeps per frame: beyond, a run is refused (docs/pipeline.md, pre-flight)


@dataclass(frozen=True)
class SimulationSettings:
    grid_resolution: int = 32  # nodes along the longest side of the domain
    domain_lower: tuple[float, float, float] | None = None  # m; None: around the object
    domain_upper: tuple[float, float, float] | None = None
    substep_dt: float | None = None  # s; None: automatic (CFL, elastic wave speed, viscosity)
    flip: float = 0.0  # PIC/FLIP blend in [0, 1] (clflow.mpm.Simulator); 0: APIC
    fps: float = 24.0
    frames: int = 24
    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)  # m/s^2
    # refuse a run (optimize, simulate) needing more substeps per frame (--max-substeps overrides)
    max_substeps: int = DEFAULT_MAX_SUBSTEPS


@dataclass(frozen=True)
class CameraConfig:
    """A camera from a 3DGS cameras.json / NeRF transforms.json entry, from an image of a
    COLMAP sparse model (by name, or ``index`` in name order), or explicit."""

    cameras_file: Path | None = None
    index: int = 0
    colmap: Path | None = None  # a sparse model folder (cameras, images as .bin or .txt)
    image: str | None = None  # the COLMAP image's name
    position: tuple[float, float, float] | None = None  # scene units
    look_at: tuple[float, float, float] | None = None
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov_y_deg: float = 50.0
    width: int = 512
    height: int = 512


@dataclass(frozen=True)
class GuidanceView:
    """A further guidance view (``camera`` and ``video`` given as lists): its camera and video."""

    camera: CameraConfig
    video: Path | None


@dataclass(frozen=True)
class GenerateSettings:
    """``video: {generate: ...}``: make the guidance video with an image-to-video model first
    (clflow.pipeline.generated_video; None values: the model's or the scene's defaults)."""

    model: Path  # a local diffusers folder (clflow.generate.inspect_model)
    prompt: str | None = None  # None: the motion prompt filled from the forces (prompt_template)
    prompt_template: str | None = None  # None: clflow.scene.video_settings.PROMPT_TEMPLATE
    object: str = "object"  # what the object is, for the template
    negative_prompt: str = ""
    image: Path | None = None  # None: the scene rendered from the guidance camera
    seed: int = 0
    frames: int | None = None  # None: enough for the simulated time, as the model makes them
    fps: float | None = None  # None: simulation.fps
    steps: int | None = None
    guidance_scale: float | None = None
    size: tuple[int, int] | None = None  # (width, height) the model generates at
    fit: str = "pad"
    cpu_offload: bool = False
    vae_tiling: bool = False
    vae_slicing: bool = False


@dataclass(frozen=True)
class FlowSettings:
    method: str = "dis"
    preset: str = DEFAULT_PRESET
    loss: str = "l2"
    mask: str = "alpha"  # "alpha" (rendered object alpha at frame 0), "none", or a file
    confidence: str = DEFAULT_CONFIDENCE  # per-pixel weight of the observed flow in the loss
    bias_correction: str = DEFAULT_BIAS_CORRECTION  # the estimator's error on the simulation, subtracted


OPTIMIZERS = ("adam", "levenberg_marquardt")


@dataclass(frozen=True)
class SearchSettings:
    """The global phase before the gradient iterations (clflow.pipeline.fit.search)."""

    samples: int = 32  # forward-only runs over the parameter box
    decades: float = 3.0  # the box of a log-scale parameter: the start times 10^(+-decades)
    frames: int = 0  # frames in the search's loss (0: all)
    starts: int = 1  # the best samples the local phase polishes (levenberg_marquardt) before keeping the best
    start_iterations: int = 3  # Levenberg-Marquardt iterations per start before they are compared
    refine: int = 0  # second-round samples, shared among the neighbourhoods of the best distinct samples
    # nodes along the domain's longest side for the search and the starts' polish (0: the
    # simulation's): a coarser grid makes the global phase cheap, the main phase keeps the finer one
    grid_resolution: int = 0


@dataclass(frozen=True)
class OptimizeSettings:
    parameters: tuple[str, ...] = ()
    learning_rates: dict[str, float] = field(default_factory=dict)  # in the optimiser's space
    iterations: int = 30
    horizon_start: int = 0  # frames in the first iteration's loss (0: all)
    horizon_step: int = 0  # frames added per iteration
    final_rate: float = 0.1  # the rate falls (cosine) to this fraction of itself by the last iteration
    search: SearchSettings | None = None  # None: no global phase
    method: str = "adam"  # the local phase: "adam" or "levenberg_marquardt" (flow loss l2 only)
    bounds: dict[str, tuple[float, float]] = field(default_factory=dict)  # SI; the search box of a parameter
    # material hypotheses: registry names, each searched before the one that fits best is
    # optimised (clflow.pipeline.hypotheses); () for the config's own material only
    materials: tuple[str, ...] = ()
    estimate_velocity_frames: int = 0  # frames in the loss of the velocity phase
    estimate_velocity_iterations: int = 0  # iterations of the velocity phase before the main one (0: none)


@dataclass(frozen=True)
class SceneConfig:
    source: Path
    splats: Path
    scale: float
    up: str
    selection: Selection
    fill: FillSettings
    material: MaterialConfig
    forces: tuple[ForceStage, ...]
    colliders: tuple[Collider, ...]
    simulation: SimulationSettings
    camera: CameraConfig
    video: Path | None
    flow: FlowSettings
    optimize: OptimizeSettings
    output: Path
    ground_truth: dict[str, float] = field(default_factory=dict)  # for metrics (RE) only; velocity as components
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)  # the object's initial velocity, m/s, scene axes
    more_views: tuple[GuidanceView, ...] = ()  # views 1.. when camera and video are lists; view 0 is camera, video
    generate: GenerateSettings | None = None  # video: {generate: ...}; video is None until it is made
    dataparser_transforms: Path | None = None  # nerfstudio's: camera files' frame -> the splat file's


def _region(r: _Reader, data: Any, path: str, allow_all: bool) -> Region:
    if data == "all" and allow_all:
        return Region("all")
    shapes = ("box", "sphere") + (("all",) if allow_all else ())
    body = r.section(data, path, ("box", "sphere"))
    if len(body) != 1:
        raise r.fail(path, f"give exactly one of {', '.join(shapes)}")
    if "box" in body:
        box = r.section(body["box"], f"{path}.box", ("min", "max"))
        lower, upper = r.vec3(box, "min", f"{path}.box"), r.vec3(box, "max", f"{path}.box")
        if not all(lo < hi for lo, hi in zip(lower, upper)):
            raise r.fail(f"{path}.box", f"min {list(lower)} must be below max {list(upper)} on every axis")
        return Region.box(lower, upper)
    sphere = r.section(body["sphere"], f"{path}.sphere", ("center", "radius"))
    return Region.sphere(
        r.vec3(sphere, "center", f"{path}.sphere"),
        r.number(sphere, "radius", f"{path}.sphere", low=0.0, strict_low=True),
    )


def _flow_mask(r: _Reader, flow_in: dict) -> str:
    """ "alpha", "none", or the resolved path of a mask image (checked to exist)."""
    mask = flow_in.get("mask")
    if mask is None or mask in ("alpha", "none"):
        return mask or "alpha"
    if not isinstance(mask, str):
        raise r.fail("flow.mask", f"must be alpha, none or a mask image file, got {mask!r}")
    return str(r.file(flow_in, "mask", "flow"))


def _window(r: _Reader, data: dict, path: str) -> tuple[float, float]:
    start = r.number(data, "start", path, 0.0, low=0.0)
    end = r.number(data, "end", path, math.inf) if data.get("end") is not None else math.inf
    if end <= start:
        raise r.fail(f"{path}.end", f"must be after start ({start:g} s), got {end:g}")
    return start, end


def _material(r: _Reader, data: Any) -> MaterialConfig:
    body = r.section(data, "material", ("type", "parameters", "density", "model", "query"))
    kind = body.get("type")
    if not isinstance(kind, str):
        raise r.fail("material.type", "is required: a material name or 'query'")
    params_in = r.mapping(body.get("parameters"), "material.parameters")  # names: the registry checks
    for name, value in params_in.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise r.fail(
                f"material.parameters.{name}",
                f"must be a number, got {value!r} (YAML reads 2e4 as text: write 2.0e+4 or 20000.0)",
            )
    if kind == "query":
        if body.get("model") is not None:
            raise r.fail("material.model", "cannot be chosen before the query picks the material type")
        query = r.section(body.get("query"), "material.query", ("image", "prompt", "backend", "result"))
        if (query.get("image") is None) == (query.get("result") is None):
            raise r.fail(
                "material.query",
                "give exactly one of image (ask the query now) and result (a record `clflow query` wrote)",
            )
        density = (
            r.number(body, "density", "material", low=0.0, strict_low=True) if body.get("density") is not None else None
        )  # None: the query's
        backend = r.choice(query, "backend", "material.query", ("offline", "openai"), "offline")
        return MaterialConfig(
            "query",
            dict(params_in),
            density,
            query_image=r.file(query, "image", "material.query", required=False),
            query_result=r.file(query, "result", "material.query", required=False),
            query_prompt=str(query.get("prompt", "")),
            query_backend=backend,
        )
    if body.get("query") is not None:
        raise r.fail("material.query", f"is only read with type: query (the type is {kind!r})")
    try:
        material = get_material(kind)
        params = validate_params(material.name, params_in)
    except InputError as exc:
        raise r.fail("material", str(exc)) from None
    density = r.number(body, "density", "material", material.default_density, low=0.0, strict_low=True)
    DENSITY.check(density)
    model = None
    if body.get("model") is not None:
        if material.name not in MATERIAL_MODELS:
            raise r.fail(
                "material.model", f"{material.name} has no model option (only {', '.join(MATERIAL_MODELS)} have)"
            )
        model = r.choice(body, "model", "material", MATERIAL_MODELS[material.name])
    return MaterialConfig(material.name, params, density, model=model)


def _forces(r: _Reader, items: list) -> tuple[ForceStage, ...]:
    stages = []
    for i, item in enumerate(items):
        path = f"forces[{i}]"
        body = r.section(item, path, ("region", "force", "acceleration", "start", "end"))
        kinds = [k for k in ("force", "acceleration") if k in body]
        if len(kinds) != 1:
            raise r.fail(path, "give exactly one of force (N) and acceleration (m/s^2)")
        start, end = _window(r, body, path)
        stages.append(
            ForceStage(
                _region(r, body.get("region", "all"), f"{path}.region", allow_all=True),
                r.vec3(body, kinds[0], path),
                kinds[0],
                start,
                end,
            )
        )
    return tuple(stages)


def _colliders(r: _Reader, data: Any) -> tuple[Collider, ...]:
    body = r.section(data, "boundaries", ("ground", "colliders"))
    out = []
    if body.get("ground") is not None:
        ground = r.section(body["ground"], "boundaries.ground", ("height", "mode", "friction"))
        out.append(
            Collider(
                (0.0, r.number(ground, "height", "boundaries.ground", 0.0), 0.0),
                (0.0, 1.0, 0.0),
                r.choice(ground, "mode", "boundaries.ground", COLLIDER_MODES, "slip"),
                r.number(ground, "friction", "boundaries.ground", 0.0, low=0.0),
            )
        )
    for i, item in enumerate(r.items(body, "colliders", "boundaries")):
        path = f"boundaries.colliders[{i}]"
        c = r.section(item, path, ("point", "normal", "mode", "friction", "start", "end"))
        normal = r.vec3(c, "normal", path)
        if not any(normal):
            raise r.fail(f"{path}.normal", "must not be the zero vector")
        start, end = _window(r, c, path)
        out.append(
            Collider(
                r.vec3(c, "point", path),
                normal,
                r.choice(c, "mode", path, COLLIDER_MODES, "slip"),
                r.number(c, "friction", path, 0.0, low=0.0),
                start,
                end,
            )
        )
    return tuple(out)


def _simulation(r: _Reader, data: Any) -> SimulationSettings:
    p = "simulation"
    body = r.section(
        data, p, ("grid_resolution", "domain", "substep_dt", "flip", "fps", "frames", "gravity", "max_substeps")
    )
    lower = upper = None
    if body.get("domain") is not None:
        dom = r.section(body["domain"], f"{p}.domain", ("min", "max"))
        lower, upper = r.vec3(dom, "min", f"{p}.domain"), r.vec3(dom, "max", f"{p}.domain")
        if not all(lo < hi for lo, hi in zip(lower, upper)):
            raise r.fail(f"{p}.domain", f"min {list(lower)} must be below max {list(upper)} on every axis")
    dt = body.get("substep_dt", "auto")
    substep_dt = None if dt == "auto" else r.number(body, "substep_dt", p, low=0.0, strict_low=True)
    return SimulationSettings(
        grid_resolution=r.integer(body, "grid_resolution", p, 32, low=11),  # walls: 4 cells a side
        domain_lower=lower,
        domain_upper=upper,
        substep_dt=substep_dt,
        flip=r.number(body, "flip", p, SimulationSettings.flip, low=0.0, high=1.0),
        fps=r.number(body, "fps", p, 24.0, low=0.0, strict_low=True),
        frames=r.integer(body, "frames", p, 24, low=1),
        gravity=r.vec3(body, "gravity", p, (0.0, -9.81, 0.0)),
        max_substeps=r.integer(body, "max_substeps", p, DEFAULT_MAX_SUBSTEPS, low=1),
    )


def _camera(r: _Reader, data: Any, p: str = "camera") -> CameraConfig:
    body = r.section(
        data, p, ("file", "colmap", "image", "index", "position", "look_at", "up", "fov_y_deg", "width", "height")
    )
    sources = [k for k in ("file", "colmap") if body.get(k) is not None]
    if not sources and body.get("position") is None:
        raise r.fail(
            p, "give a camera file (cameras.json / transforms.json), a COLMAP model (colmap) or position and look_at"
        )
    if len(sources) > 1:
        raise r.fail(p, "give file or colmap, not both")
    explicit = not sources
    ignored = [k for k in ("position", "look_at", "up", "fov_y_deg", "width", "height") if k in body]
    if not explicit and ignored:
        what = "file" if sources[0] == "file" else "model"
        raise r.fail(p, f"with a camera {what}, {', '.join(ignored)} come from the {what}: drop them")
    if explicit and "index" in body:
        raise r.fail(f"{p}.index", "picks an entry of a camera file or model: give file or colmap as well, or drop it")
    if "image" in body and "colmap" not in body:
        raise r.fail(f"{p}.image", "names an image of a COLMAP model: give colmap as well, or drop it")
    if "image" in body and "index" in body:
        raise r.fail(p, "give image or index, not both")
    image = body.get("image")
    if image is not None and (not isinstance(image, str) or not image):
        raise r.fail(f"{p}.image", f"must be an image name of the COLMAP model, got {image!r}")
    return CameraConfig(
        cameras_file=r.file(body, "file", p, required=False),
        index=r.integer(body, "index", p, 0),
        colmap=r.file(body, "colmap", p, required=False, folder_ok=True),
        image=image,
        position=r.vec3(body, "position", p) if explicit else None,
        look_at=r.vec3(body, "look_at", p) if explicit else None,
        up=r.vec3(body, "up", p, (0.0, 1.0, 0.0)),
        fov_y_deg=r.number(body, "fov_y_deg", p, 50.0, low=1.0, high=179.0),
        width=r.integer(body, "width", p, 512, low=8),
        height=r.integer(body, "height", p, 512, low=8),
    )


def _views(r: _Reader, top: dict) -> tuple[list[CameraConfig], list[Path | None]]:
    """The guidance views: ``camera`` and ``video`` each one entry or a list of one per view."""
    cameras, videos = top.get("camera"), top.get("video")
    if isinstance(videos, dict):  # video: {generate: ...}: one view, its video made later
        if isinstance(cameras, list) and len(cameras) != 1:
            raise r.fail(
                "video.generate",
                f"makes one guidance view's video; with {len(cameras)} cameras give a list of video files",
            )
        return [_camera(r, cameras[0] if isinstance(cameras, list) else cameras)], [None]
    for key, value in (("camera", cameras), ("video", videos)):
        if isinstance(value, list) and not value:
            raise r.fail(key, "is an empty list: give one entry per guidance view")
    if not isinstance(cameras, list):
        cameras = [cameras]
    if videos is not None and not isinstance(videos, list):
        videos = [videos]
    if videos is not None and len(videos) != len(cameras):
        raise r.fail("video", f"has {len(videos)} entries, camera {len(cameras)}: give one video per camera")
    if len(cameras) == 1:  # one view: the keys read as always (error messages without an index)
        return [_camera(r, cameras[0])], [
            r.file({"video": videos and videos[0]}, "video", "", required=False, folder_ok=True)
        ]
    return (
        [_camera(r, c, f"camera[{i}]") for i, c in enumerate(cameras)],
        [None] * len(cameras)
        if videos is None
        else [r.file({f"video[{i}]": v}, f"video[{i}]", "", folder_ok=True) for i, v in enumerate(videos)],
    )


def _generate(r: _Reader, data: Any, simulation: SimulationSettings) -> GenerateSettings | None:
    """``video: {generate: {...}}``, its model folder and request checked as far as they can
    be before the scene is loaded (clflow.generate.check_request; the JSON files only)."""
    if not isinstance(data, dict):
        return None
    p = "video.generate"
    outer = r.section(data, "video", ("generate",))
    body = r.section(
        outer.get("generate"),
        p,
        (
            "model",
            "prompt",
            "prompt_template",
            "object",
            "negative_prompt",
            "image",
            "seed",
            "frames",
            "fps",
            "steps",
            "guidance_scale",
            "size",
            "fit",
            "cpu_offload",
            "vae_tiling",
            "vae_slicing",
        ),
    )
    if not body:
        raise r.fail(p, "is required: at least the model folder (video: {generate: {model: ...}})")
    model = body.get("model")
    if not isinstance(model, str) or not model:
        raise r.fail(f"{p}.model", f"is required: a local diffusers model folder, got {model!r}")
    texts = {}
    for key in ("prompt", "prompt_template", "object", "negative_prompt"):
        value = body.get(key)
        if value is not None and not isinstance(value, str):
            raise r.fail(f"{p}.{key}", f"must be text, got {value!r}")
        texts[key] = value
    flags = {}
    for key in ("cpu_offload", "vae_tiling", "vae_slicing"):
        flags[key] = body.get(key, False)
        if not isinstance(flags[key], bool):
            raise r.fail(f"{p}.{key}", f"must be true or false, got {flags[key]!r}")
    size = None
    if body.get("size") is not None:
        value = body["size"]
        if (
            isinstance(value, list)
            and len(value) == 2
            and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in value)
        ):
            size = (value[0], value[1])
        elif isinstance(value, str):
            from clflow.generate import parse_size

            try:
                size = parse_size(value)
            except InputError as exc:
                raise r.fail(f"{p}.size", str(exc)) from None
        else:
            raise r.fail(f"{p}.size", f"must be WIDTHxHEIGHT or [width, height] in pixels, got {value!r}")
    settings = GenerateSettings(
        model=(r.base / model).resolve(),
        prompt=texts["prompt"],
        prompt_template=texts["prompt_template"],
        object=texts["object"] or "object",
        negative_prompt=texts["negative_prompt"] or "",
        image=r.file(body, "image", p, required=False),
        seed=r.integer(body, "seed", p, 0),
        frames=r.integer(body, "frames", p, low=2) if body.get("frames") is not None else None,
        fps=r.number(body, "fps", p, low=0.0, strict_low=True) if body.get("fps") is not None else None,
        steps=r.integer(body, "steps", p, low=1) if body.get("steps") is not None else None,
        guidance_scale=r.number(body, "guidance_scale", p, low=0.0) if body.get("guidance_scale") is not None else None,
        size=size,
        fit=r.choice(body, "fit", p, ("pad", "crop"), "pad"),
        **flags,
    )
    from clflow.scene.video_settings import check_settings

    check_settings(settings, simulation, fail=lambda key, message: r.fail(f"{p}.{key}" if key else p, message))
    return settings


def _optimize_settings(r: _Reader, data: Any, material: MaterialConfig, frames: int) -> OptimizeSettings:
    p = "optimize"
    body = r.section(
        data,
        p,
        (
            "parameters",
            "learning_rates",
            "iterations",
            "horizon",
            "final_rate",
            "search",
            "bounds",
            "method",
            "estimate_velocity",
            "material",
        ),
    )
    names = body.get("parameters", [])
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise r.fail(f"{p}.parameters", f"must be a list of parameter names, got {names!r}")
    hypotheses = _hypotheses(r, body.get("material"), names)
    if material.type != "query" and not hypotheses:
        mat = get_material(material.type)
        for name in names:
            if name not in ("density", VELOCITY) and name not in mat.param_names:
                raise r.fail(
                    f"{p}.parameters",
                    f"{name!r} is not a parameter of {mat.name} "
                    f"(its parameters: {', '.join(mat.param_names)}, density, velocity)",
                )
    estimate = r.section(body.get("estimate_velocity"), f"{p}.estimate_velocity", ("frames", "iterations"))
    estimate_frames = estimate_iterations = 0
    if estimate:
        estimate_frames = r.integer(estimate, "frames", f"{p}.estimate_velocity", low=1)
        estimate_iterations = r.integer(estimate, "iterations", f"{p}.estimate_velocity", low=1)
        if estimate_frames > frames:
            raise r.fail(
                f"{p}.estimate_velocity.frames", f"must be <= simulation.frames ({frames}), got {estimate_frames}"
            )
    rates_in = r.mapping(body.get("learning_rates"), f"{p}.learning_rates")
    for name in rates_in:
        if name not in names and not (name == VELOCITY and estimate):
            raise r.fail(
                f"{p}.learning_rates.{name}",
                f"is not among optimize.parameters {names}"
                + (" (nor estimated: optimize.estimate_velocity)" if name == VELOCITY else ""),
            )
    rates = {n: r.number(rates_in, n, f"{p}.learning_rates", low=0.0, strict_low=True) for n in rates_in}
    horizon = r.section(body.get("horizon"), f"{p}.horizon", ("start", "step"))
    search = SearchSettings() if hypotheses else None  # hypotheses are told apart by the search
    if body.get("search") is not None:
        found = r.section(
            body["search"],
            f"{p}.search",
            ("samples", "decades", "frames", "starts", "start_iterations", "refine", "grid_resolution"),
        )
        search = SearchSettings(
            samples=r.integer(found, "samples", f"{p}.search", 32, low=1),
            decades=r.number(found, "decades", f"{p}.search", 3.0, low=0.0, strict_low=True),
            frames=r.integer(found, "frames", f"{p}.search", 0),
            starts=r.integer(found, "starts", f"{p}.search", 1, low=1),
            start_iterations=r.integer(found, "start_iterations", f"{p}.search", 3, low=1),
            refine=r.integer(found, "refine", f"{p}.search", 0),
            grid_resolution=r.integer(found, "grid_resolution", f"{p}.search", 0),
        )
        if 0 < search.grid_resolution < 11:  # as simulation.grid_resolution: walls take 4 cells a side
            raise r.fail(
                f"{p}.search.grid_resolution", f"must be 0 (the simulation's) or >= 11, got {search.grid_resolution}"
            )
        if search.starts > search.samples:
            raise r.fail(
                f"{p}.search.starts", f"must not exceed search.samples ({search.samples}), got {search.starts}"
            )
    bounds = {}
    for name, box in r.mapping(body.get("bounds"), f"{p}.bounds").items():
        where = f"{p}.bounds.{name}"
        if name not in names:
            raise r.fail(where, f"is not among optimize.parameters {names}")
        if (
            not isinstance(box, list)
            or len(box) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in box)
        ):
            raise r.fail(where, f"must be [lower, upper] (SI), got {box!r}")
        if not box[0] < box[1]:
            raise r.fail(where, f"is empty or inverted: lower {box[0]:g} must be below upper {box[1]:g}")
        bounds[name] = (float(box[0]), float(box[1]))
    return OptimizeSettings(
        parameters=tuple(names),
        learning_rates=rates,
        iterations=r.integer(body, "iterations", p, 30, low=1),
        horizon_start=r.integer(horizon, "start", f"{p}.horizon", 0),
        horizon_step=r.integer(horizon, "step", f"{p}.horizon", 0),
        final_rate=r.number(body, "final_rate", p, 0.1, low=0.0, high=1.0),
        search=search,
        bounds=bounds,
        method=r.choice(body, "method", p, OPTIMIZERS, "adam"),
        estimate_velocity_frames=estimate_frames,
        estimate_velocity_iterations=estimate_iterations,
        materials=hypotheses,
    )


def _hypotheses(r: _Reader, data: Any, names: list[str]) -> tuple[str, ...]:
    """``optimize.material``: registry names (aliases resolved), each with at least one of
    ``optimize.parameters``; every parameter belongs to at least one of them."""
    p = "optimize.material"
    if data is None:
        return ()
    if not isinstance(data, list) or not data or not all(isinstance(n, str) for n in data):
        raise r.fail(p, f"must be a non-empty list of material names, got {data!r}")
    try:
        materials = [get_material(n) for n in data]
    except InputError as exc:
        raise r.fail(p, str(exc)) from None
    canonical = [m.name for m in materials]
    if len(set(canonical)) < len(canonical):
        raise r.fail(p, f"names a material twice: {data!r}")
    common = ("density", VELOCITY)
    for m in materials:
        if not any(n in common or n in m.param_names for n in names):
            raise r.fail(
                p,
                f"{m.name} has none of optimize.parameters {names} (its parameters: "
                f"{', '.join(m.param_names)}, density, velocity)",
            )
    for n in names:
        if n not in common and not any(n in m.param_names for m in materials):
            raise r.fail(
                "optimize.parameters", f"{n!r} is a parameter of none of the hypotheses {', '.join(canonical)}"
            )
    return tuple(canonical)


TOP_KEYS = (
    "splats",
    "scene",
    "object",
    "material",
    "forces",
    "boundaries",
    "simulation",
    "camera",
    "video",
    "flow",
    "optimize",
    "evaluation",
    "output",
)


def parse_config(data: Any, source: str = "<config>", base: Path | None = None) -> SceneConfig:
    """Validate a parsed config (dict) and return a :class:`SceneConfig`."""
    r = _Reader(source, base or Path.cwd())
    top = r.section(data, "", TOP_KEYS)
    if not top:
        raise r.fail("", "the config is empty")
    scene = r.section(top.get("scene"), "scene", ("scale", "up", "dataparser_transforms"))
    obj = r.section(top.get("object"), "object", ("select", "fill", "velocity"))
    select = r.section(obj.get("select"), "object.select", ("box", "sphere", "mask", "ply", "tolerance"))
    if not select:
        raise r.fail("object.select", "is required: a box, a sphere, a mask file or a PLY of the part")
    if "tolerance" in select and "ply" not in select:
        raise r.fail("object.select.tolerance", "applies to a ply selection only: drop it")
    if len(set(select) & {"box", "sphere", "mask", "ply"}) > 1:
        raise r.fail("object.select", "give exactly one of box, sphere, mask and ply")
    if "mask" in select:
        selection = Selection(None, r.file(select, "mask", "object.select"))
    elif "ply" in select:
        tolerance = select.get("tolerance")
        selection = Selection(
            None,
            None,
            r.file(select, "ply", "object.select"),
            None if tolerance is None else r.number(select, "tolerance", "object.select", low=0.0, strict_low=True),
        )
    else:
        selection = Selection(_region(r, select, "object.select", allow_all=False), None)
    fill_in = r.section(obj.get("fill"), "object.fill", ("enabled", "spacing", "per_axis"))
    enabled = fill_in.get("enabled", True)
    if not isinstance(enabled, bool):
        raise r.fail("object.fill.enabled", f"must be true or false, got {enabled!r}")
    fill = FillSettings(
        enabled=enabled,
        spacing=r.number(fill_in, "spacing", "object.fill", low=0.0, strict_low=True)
        if fill_in.get("spacing") is not None
        else None,
        per_axis=r.integer(fill_in, "per_axis", "object.fill", 1, low=1),
    )
    material = _material(r, top.get("material"))
    flow_in = r.section(top.get("flow"), "flow", ("method", "preset", "loss", "mask", "confidence", "bias_correction"))
    flow = FlowSettings(
        method=r.choice(flow_in, "method", "flow", FLOW_METHODS, "dis"),
        preset=r.choice(flow_in, "preset", "flow", DIS_PRESETS, DEFAULT_PRESET),
        loss=r.choice(flow_in, "loss", "flow", FLOW_LOSSES, "l2"),
        mask=_flow_mask(r, flow_in),
        confidence=r.choice(flow_in, "confidence", "flow", CONFIDENCES, DEFAULT_CONFIDENCE),
        bias_correction=r.choice(flow_in, "bias_correction", "flow", BIAS_CORRECTIONS, DEFAULT_BIAS_CORRECTION),
    )
    evaluation = r.section(top.get("evaluation"), "evaluation", ("ground_truth",))
    truth = dict(r.mapping(evaluation.get("ground_truth"), "evaluation.ground_truth"))
    true_velocity = r.vec3(truth, VELOCITY, "evaluation.ground_truth", ())  # () when not given
    truth.pop(VELOCITY, None)
    for name, value in truth.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise r.fail(f"evaluation.ground_truth.{name}", f"must be a number, got {value!r}")
    true_density = truth.pop("density", None)
    if true_density is not None:
        try:
            DENSITY.check(true_density)
        except InputError as exc:
            raise r.fail("evaluation.ground_truth", str(exc)) from None
    simulation = _simulation(r, top.get("simulation"))
    output = top.get("output", "results")
    if not isinstance(output, str) or not output:
        raise r.fail("output", f"must be a folder path, got {output!r}")
    optimize = _optimize_settings(r, top.get("optimize"), material, simulation.frames)
    if truth and (optimize.materials or material.type != "query"):
        # with hypotheses, the truth's material is one of them: the first that has all its names
        candidates = optimize.materials or (material.type,)
        fitting = [m for m in candidates if set(truth) <= set(get_material(m).param_names)] or candidates[:1]
        try:
            truth = {k: v for k, v in validate_params(fitting[0], truth).items() if k in truth}
        except InputError as exc:
            raise r.fail("evaluation.ground_truth", str(exc)) from None
    if true_density is not None:
        truth["density"] = float(true_density)
    truth.update(zip(VELOCITY_COMPONENTS, true_velocity))
    if optimize.search is not None and optimize.search.starts > 1 and optimize.method != "levenberg_marquardt":
        raise r.fail(
            "optimize.search.starts",
            "several starts are polished by levenberg_marquardt: set "
            "optimize.method: levenberg_marquardt, or starts: 1",
        )
    if optimize.search is not None and optimize.search.grid_resolution > simulation.grid_resolution:
        raise r.fail(
            "optimize.search.grid_resolution",
            f"must not exceed simulation.grid_resolution ({simulation.grid_resolution}): the search's "
            f"grid is the coarse one, got {optimize.search.grid_resolution}",
        )
    if optimize.method == "levenberg_marquardt" and flow.loss != "l2":
        raise r.fail(
            "optimize.method", f"levenberg_marquardt minimises a sum of squares: it needs flow.loss l2, not {flow.loss}"
        )
    cameras, videos = _views(r, top)
    if len(cameras) > 1 and flow.mask not in ("alpha", "none"):
        raise r.fail("flow.mask", "a mask image fits one view: with several guidance views use alpha or none")
    return SceneConfig(
        source=Path(source),
        splats=r.file(top, "splats", ""),
        scale=r.number(scene, "scale", "scene", 1.0, low=0.0, strict_low=True),
        up=r.choice(scene, "up", "scene", UP_AXES, "+y"),
        selection=selection,
        fill=fill,
        material=material,
        forces=_forces(r, r.items(top, "forces", "")),
        colliders=_colliders(r, top.get("boundaries")),
        simulation=simulation,
        camera=cameras[0],
        video=videos[0],  # a video or an image folder
        flow=flow,
        optimize=optimize,
        output=(r.base / output).resolve(),
        ground_truth=dict(truth),
        velocity=r.vec3(obj, "velocity", "object", (0.0, 0.0, 0.0)),
        more_views=tuple(GuidanceView(c, v) for c, v in zip(cameras[1:], videos[1:])),
        dataparser_transforms=r.file(scene, "dataparser_transforms", "scene", required=False),
        generate=_generate(r, top.get("video"), simulation),
    )


def _dotted(path: str, key: object) -> str:
    """``path`` extended by a mapping key (``a.b``) or a list index (``a[0]``)."""
    if isinstance(key, int):
        return f"{path}[{key}]"
    return f"{path}.{key}" if path else str(key)


class _JsonPairs(list):
    """A JSON object as its (key, value) pairs, so duplicate keys survive parsing."""


def _json_without_duplicates(value: Any, path: str = "") -> Any:
    """Turn parsed :class:`_JsonPairs` into dicts; a key given twice raises with its dotted path."""
    if isinstance(value, _JsonPairs):
        out: dict[str, Any] = {}
        for key, item in value:
            if key in out:
                raise _DuplicateKey(_dotted(path, key))
            out[key] = _json_without_duplicates(item, _dotted(path, key))
        return out
    if isinstance(value, list):
        return [_json_without_duplicates(item, _dotted(path, i)) for i, item in enumerate(value)]
    return value


class _DuplicateKey(Exception):
    """A mapping key given twice; the argument is its dotted path (and YAML line)."""


def _load_json(text: str) -> Any:
    return _json_without_duplicates(json.loads(text, object_pairs_hook=_JsonPairs))


#: A number with an exponent that YAML 1.1 (PyYAML) reads as a string: no dot (``2e4``) or
#: no sign in the exponent (``2.0e4``). YAML 1.2 and JSON read them as numbers, and so do we.
_EXPONENT_FLOAT = re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$")


def _load_yaml(text: str) -> Any:
    """``yaml.safe_load`` that reads ``2e4`` as a float and rejects a mapping key given twice
    (PyYAML keeps the last)."""
    import yaml

    class StrictLoader(yaml.SafeLoader):
        def construct_document(self, node):
            self._check_duplicates(node, "")
            return super().construct_document(node)

        def _check_duplicates(self, node, path: str) -> None:
            if isinstance(node, yaml.MappingNode):
                seen = set()
                for key_node, value_node in node.value:
                    key = key_node.value if isinstance(key_node, yaml.ScalarNode) else None
                    if key is not None and key != "<<":
                        if key in seen:
                            line = key_node.start_mark.line + 1
                            raise _DuplicateKey(f"{_dotted(path, key)} (line {line})")
                        seen.add(key)
                    self._check_duplicates(value_node, _dotted(path, key))
            elif isinstance(node, yaml.SequenceNode):
                for i, item in enumerate(node.value):
                    self._check_duplicates(item, _dotted(path, i))

    StrictLoader.add_implicit_resolver("tag:yaml.org,2002:float", _EXPONENT_FLOAT, list("-+0123456789."))
    return yaml.load(text, Loader=StrictLoader)


def load_config(path: str | Path, overrides: Sequence[str] = ()) -> SceneConfig:
    """Read and validate a YAML (.yaml/.yml) or JSON (.json) scene config.

    ``overrides``: ``key.sub=value`` strings (the CLI's ``--set``), each value read as YAML
    (``2e4``, ``[0, 1, 0]``, ``auto``), set over the file's before the whole is validated.
    """
    from clflow.fileio import read_text

    path = Path(path)
    text = read_text(path, "config")
    loader: Callable[[str], Any]
    if path.suffix.lower() == ".json":
        loader = _load_json
        errors: tuple[type[Exception], ...] = (json.JSONDecodeError,)
    else:
        import yaml

        loader, errors = _load_yaml, (yaml.YAMLError,)
    try:
        data = loader(text)
    except errors as exc:
        raise InputError(f"{path}: not valid {'JSON' if path.suffix.lower() == '.json' else 'YAML'}: {exc}") from None
    except _DuplicateKey as exc:
        raise InputError(f"{path}: {exc}: duplicate key (each key may appear only once)") from None
    data = {} if data is None else data
    keys = {}
    for item in overrides:
        keys[_override(data, item)] = item
    try:
        return parse_config(data, str(path), path.parent.resolve())
    except InputError as exc:
        # name the --set that brought in the bad key or value, not only the file
        where = str(exc).removeprefix(f"{path}: ").split(":")[0]
        for key, item in keys.items():
            if key == where or key.startswith((where + ".", where + "[")) or where.startswith(key + "."):
                raise InputError(f"--set {item}: {str(exc).removeprefix(f'{path}: ')}") from None
        raise


def _override(data: Any, item: str) -> str:
    """Set ``key.sub=value`` (value read as YAML) in the parsed config ``data``, making the
    mappings on the way; a number as a part indexes an existing list item (``forces.0.end``).
    Returns the key as the config's messages write it (``forces[0].end``)."""
    import yaml

    key, sep, text = item.partition("=")
    parts = key.strip().split(".")
    if not sep or not all(re.fullmatch(r"[A-Za-z0-9_]+", p) for p in parts) or parts[0].isdigit():
        raise InputError(
            f"--set {item}: expected KEY.SUB=VALUE with a dotted key of config names (a number "
            f"for a list item), e.g. simulation.frames=24 or forces.0.end=0.5"
        )
    try:
        value = _load_yaml(text)
    except (yaml.YAMLError, _DuplicateKey) as exc:
        raise InputError(f"--set {item}: the value is not valid YAML ({' '.join(str(exc).split())})") from None
    node, walked = data, ""
    for k, part in enumerate(parts):
        last = k == len(parts) - 1
        if isinstance(node, list) and part.isdigit():
            index = int(part)
            if index >= len(node):
                raise InputError(
                    f"--set {item}: {walked} has {len(node)} item(s), so no item {index} "
                    f"(items count from 0; add new ones in the config file)"
                )
            if last:
                node[index] = value
            else:
                node = node[index]
            walked += f"[{index}]"
            continue
        if not isinstance(node, dict):
            where = walked or "the config"
            raise InputError(f"--set {item}: {where} is a {type(node).__name__} in the config, not a mapping of keys")
        if last:
            node[part] = value
        else:
            if node.get(part) is None:
                if parts[k + 1].isdigit():
                    raise InputError(
                        f"--set {item}: {walked + '.' if walked else ''}{part} is not in the config: "
                        f"set the whole list ({walked + '.' if walked else ''}{part}=[...])"
                    )
                node[part] = {}
            node = node[part]
        walked += f".{part}" if walked else part
    return walked
