"""The scene config's sections and their keys, declared once.

A section's keys are the fields of its settings dataclass (``clflow.scene.config.settings``,
declared with ``keys.setting``) or, where no dataclass field holds the key, :class:`Key`
values here. The reader takes its allowed keys, defaults and ranges from :data:`SECTIONS`;
``clflow.scene.config.doc`` writes the tables of docs/scene_config.md from it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from clflow.scene.config.keys import (
    ACCELERATION,
    FORCE,
    LENGTH,
    SCALE,
    SCENE_LENGTH,
    Key,
    keys_of,
)
from clflow.scene.config.optimize_settings import BudgetSettings, OptimizeSettings, SearchSettings
from clflow.scene.config.settings import (
    UP_AXES,
    CameraConfig,
    Collider,
    FillSettings,
    FlowSettings,
    GenerateSettings,
    MaterialConfig,
    SceneObject,
    SimulationSettings,
)


@dataclass(frozen=True)
class Section:
    """The keys of one config section (``path`` as messages write it; ``[i]`` and ``NAME``
    stand for any item). A dotted key name (``domain.min``) is a key of a sub-section:
    ``known`` lists the section's own keys, in ``order`` where messages list them otherwise
    than the keys come."""

    path: str
    keys: tuple[Key, ...]
    order: tuple[str, ...] = ()

    def __post_init__(self):
        assert not self.order or sorted(self.order) == sorted(self._heads()), self.path

    def _heads(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(k.name.partition(".")[0] for k in self.keys))

    @property
    def known(self) -> tuple[str, ...]:
        """The keys the section takes, as the unknown-key message lists them."""
        return self.order or self._heads()

    def __getitem__(self, name: str) -> Key:
        return next(k for k in self.keys if k.name == name)

    def sub(self, head: str, order: tuple[str, ...] = ()) -> Section:
        """The sub-section ``head`` of the dotted keys ``head.NAME``."""
        keys = tuple(replace(k, name=k.name[len(head) + 1 :]) for k in self.keys if k.name.startswith(head + "."))
        return Section(f"{self.path}.{head}", keys, order)


def _region(path: str, limit: float, unit: str) -> tuple[Section, Section]:
    """A region's box and sphere (``path``: the region's), within +-``limit`` (``unit``, its
    frame's length)."""
    box = Section(
        f"{path}.box",
        (
            Key(
                "min",
                "vec3",
                "the box's lower corner, below `max` on every axis (bounds inclusive)",
                unit=unit,
                high=limit,
            ),
            Key("max", "vec3", "its upper corner", unit=unit, high=limit),
        ),
    )
    sphere = Section(
        f"{path}.sphere",
        (
            Key("center", "vec3", "the sphere's centre", unit=unit, high=limit),
            Key("radius", "number", "the sphere's radius", unit=unit, low=0.0, high=limit, strict_low=True),
        ),
    )
    return box, sphere


TOP = Section(
    "",
    (
        Key("splats", "file", "a 3DGS PLY file (or a compressed `.compressed.ply`, as SuperSplat writes)"),
        Key("scene", "section", "the splat file's scale and axes", shown=""),
        Key("object", "section", "the one object's Gaussians, fill and velocity (with `material`)", shown=""),
        Key("material", "section", "the one object's material (with `object`)", shown=""),
        Key(
            "objects",
            "other",
            "several objects: a non-empty list of entries with a `name`, or a mapping of names to entries, each "
            "its own select, fill, velocity and material; not with `object` or `material`",
            shown="",
        ),
        Key("forces", "list", "force stages", shown="none"),
        Key("boundaries", "section", "the ground and colliders", shown="none"),
        Key("simulation", "section", "the simulation's grid, time and gravity", shown=""),
        Key("camera", "other", "the guidance camera (or a list of one per guidance view)"),
        Key(
            "video",
            "other",
            "a video file (`.mp4 .avi .webm .mkv .mov .gif`) or a folder of numbered images, or a list of them, "
            "one per `camera` entry, or `{generate: ...}` (below); required by `clflow optimize` *(run)*",
            default=None,
        ),
        Key("flow", "section", "the observed flow and the loss", shown=""),
        Key("optimize", "section", "what to optimise, and how", shown=""),
        Key("evaluation", "section", "known values, for metrics", shown="none"),
        Key("output", "text", "a non-empty folder path", default="results"),
    ),
)
SCENE = Section(
    "scene",
    (
        Key("scale", "number", "metres per scene unit", default=1.0, low=SCALE[0], high=SCALE[1]),
        Key("up", "choice", "the file's up axis, turned to +y", default="+y", choices=UP_AXES),
        Key(
            "dataparser_transforms",
            "file",
            "nerfstudio's `dataparser_transforms.json` (`transform` 3x4, a rotation and translation, and `scale`) "
            "of a splatfacto export: cameras read from `camera.file` / `camera.colmap` (the capture's frame) are "
            "moved into the splat file's frame, x_model = scale (R x + t); explicit cameras are already in it. "
            "Give the `transforms.json` nerfstudio trained on as `camera.file`, not the COLMAP model it came from: "
            "nerfstudio turns COLMAP's world axes when it imports a model (`ns-process-data` records that as "
            "`applied_transform` in the file), a turn the dataparser transform does not include",
            default=None,
        ),
    ),
)
_SELECT = Key(
    "select",
    "section",
    "exactly one of `box`, `sphere`, `mask`, `ply`; picks Gaussians by their centres in scene units",
)
_FILL = Key("fill", "section", "particles inside the object besides the Gaussian centres", shown="")
_MATERIAL = Key(
    "material", "section", "as the `material` section: `type` (or `query`), `parameters`, `model`, `density`"
)
OBJECT = Section("object", (_SELECT, _FILL, *keys_of(SceneObject)))
OBJECT_ENTRY = Section("objects.NAME", (*OBJECT.keys, _MATERIAL))  # an entry of the mapping form
OBJECT_ITEM = Section(  # an entry of the list form
    "objects[i]",
    (
        Key(
            "name",
            "text",
            "letters, digits and `_`, not starting with a digit; unique (a name given twice is an error). "
            "In a mapping, the key is the name",
            shown="required in a list",
        ),
        *OBJECT_ENTRY.keys,
    ),
)
SELECT = Section(
    "object.select",
    (
        Key("box", "section", "`min`, `max`: a box", shown=""),
        Key("sphere", "section", "`center`, `radius`: a sphere", shown=""),
        Key(
            "mask", "file", "an `.npy` file: N booleans, or a 1-D array of integer indices in [0, N) *(run)*", shown=""
        ),
        Key(
            "ply",
            "file",
            "a PLY of the part (3DGS or `x y z` points), e.g. the selection a splat editor (SuperSplat, ...) "
            "exported from the same file: every Gaussian of the scene within `tolerance` of one of the part's "
            "centres is the object; none matching is an error, some of the part's centres matching none is "
            "logged *(run)*",
            shown="",
        ),
        Key(
            "tolerance",
            "number",
            "only with `ply`",
            unit="scene units",
            low=0.0,
            high=SCENE_LENGTH,
            strict_low=True,
            default=None,
            shown="1e-5 of the scene's diagonal (plus the quantisation error of a compressed part)",
        ),
    ),
)
SELECT_BOX, SELECT_SPHERE = _region("object.select", SCENE_LENGTH, "scene units")
FILL = Section("object.fill", keys_of(FillSettings))
MATERIAL = Section("material", keys_of(MaterialConfig))
QUERY = MATERIAL.sub("query", order=("image", "prompt", "backend", "result"))  # the order messages list them
_WINDOW = {k.name: k for k in keys_of(Collider)}  # start, end: as a collider's
FORCE_STAGE = Section(
    "forces[i]",
    (
        Key(
            "region",
            "other",
            "`all`, or exactly one of `box` (min < max) and `sphere` (radius > 0); m, simulation frame",
            default="all",
        ),
        Key("force", "vec3", "N in total, shared by mass; exactly one of `force` and `acceleration`", high=FORCE),
        Key("acceleration", "vec3", "m/s^2; exactly one of `force` and `acceleration`", high=ACCELERATION),
        _WINDOW["start"],
        replace(_WINDOW["end"], doc="> `start`: the stage acts during [`start`, `end`)"),
    ),
)
REGION = Section(
    "forces[i].region",
    (
        Key("box", "section", "`min`, `max`: a box", shown=""),
        Key("sphere", "section", "`center`, `radius`: a sphere", shown=""),
    ),
)
REGION_BOX, REGION_SPHERE = _region(REGION.path, LENGTH, "m")
BOUNDARIES = Section(
    "boundaries",
    (
        Key("ground", "section", "the half-space below y = height; always active", shown="no ground"),
        Key("colliders", "list", "more half-spaces", shown="none"),
    ),
)
GROUND = Section(
    "boundaries.ground",
    (
        Key("height", "number", "the solid is y < height", unit="m", default=0.0, low=-LENGTH, high=LENGTH),
        _WINDOW["mode"],
        _WINDOW["friction"],
    ),
)
COLLIDER = Section("boundaries.colliders[i]", keys_of(Collider))
SIMULATION = Section("simulation", keys_of(SimulationSettings))
DOMAIN = SIMULATION.sub("domain")
CAMERA = Section(
    "camera",
    keys_of(CameraConfig),
    # the order messages list them
    order=("file", "colmap", "image", "index", "position", "look_at", "up", "fov_y_deg", "width", "height"),
)
VIDEO = Section(
    "video", (Key("generate", "section", "make the guidance video with an image-to-video model", shown=""),)
)
GENERATE = Section("video.generate", keys_of(GenerateSettings))
FLOW = Section("flow", keys_of(FlowSettings))
OPTIMIZE = Section(
    "optimize",
    keys_of(OptimizeSettings),
    order=(  # the order messages list them
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
        "prior",
        "budget",
    ),
)
HORIZON = OPTIMIZE.sub("horizon")
ESTIMATE_VELOCITY = OPTIMIZE.sub("estimate_velocity")
SEARCH = Section("optimize.search", keys_of(SearchSettings))
BUDGET = Section("optimize.budget", keys_of(BudgetSettings))
EVALUATION = Section(
    "evaluation",
    (
        Key(
            "ground_truth",
            "mapping",
            "known parameter values, checked like `material.parameters`, `density`, and `velocity` (3 numbers "
            "within +-1e4, m/s, in the frame of `object.velocity`); several objects: `OBJECT.PARAM` (see `objects`)",
            default=None,
        ),
    ),
)

#: Every section, by its path.
SECTIONS: dict[str, Section] = {
    s.path: s
    for s in (
        TOP,
        SCENE,
        OBJECT,
        OBJECT_ENTRY,
        OBJECT_ITEM,
        SELECT,
        SELECT_BOX,
        SELECT_SPHERE,
        FILL,
        MATERIAL,
        QUERY,
        FORCE_STAGE,
        REGION,
        REGION_BOX,
        REGION_SPHERE,
        BOUNDARIES,
        GROUND,
        COLLIDER,
        SIMULATION,
        DOMAIN,
        CAMERA,
        VIDEO,
        GENERATE,
        FLOW,
        OPTIMIZE,
        HORIZON,
        ESTIMATE_VELOCITY,
        SEARCH,
        BUDGET,
        EVALUATION,
    )
}
