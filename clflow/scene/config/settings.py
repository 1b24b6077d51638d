"""The scene config's types, section by section, and the names and choices its keys take;
a field a key sets declares it (``keys.setting``: kind, unit, default, range, meaning), which
clflow.scene.config.parse reads and checks it by (the ``optimize`` section's types:
``optimize_settings``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

from clflow.flow.optical_flow import (
    BIAS_CORRECTIONS,
    CONFIDENCES,
    DEFAULT_BIAS_CORRECTION,
    DEFAULT_CONFIDENCE,
    DEFAULT_PRESET,
    DIS_PRESETS,
)
from clflow.materials import DENSITY
from clflow.mpm.constants import COLLIDER_MODES
from clflow.mpm.material_model import ELASTIC_MODELS, SAND_MODELS
from clflow.regions import Region
from clflow.scene.config.keys import (
    ACCELERATION,
    FPS,
    LENGTH,
    MAX_GRID,
    MAX_PER_AXIS,
    MAX_PIXELS,
    SCENE_LENGTH,
    SPEED,
    setting,
)
from clflow.scene.config.optimize_settings import VELOCITY, VELOCITY_COMPONENTS, OptimizeSettings

UP_AXES = ("+x", "-x", "+y", "-y", "+z", "-z")
FLOW_METHODS = ("dis", "farneback")
FLOW_LOSSES = ("l2", "charbonnier")
#: flow.stabilise: ``static`` registers the guidance to its first frame's camera and exposure
#: over the pixels outside the objects (clflow.flow.stabilise); ``none`` takes it as it is
STABILISATIONS = ("static", "none")
MATERIAL_MODELS = {"elastic": ELASTIC_MODELS, "sand": SAND_MODELS}  # material.model options


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
    """An object's ``fill``: particles inside it besides the Gaussian centres."""

    enabled: bool = setting(True, kind="flag", doc="fill the inside with particles")
    spacing: float | None = setting(  # None: half the grid spacing (8 particles per cell)
        None,
        kind="number",
        unit="m",
        low=1e-6,
        high=LENGTH,
        shown="`dx / 2`",
        doc="the voxel size of the fill grid (at most 256^3 voxels, and particles that fit in the machine's "
        "memory *(run)*)",
    )
    per_axis: int = setting(
        1, kind="integer", low=1, high=MAX_PER_AXIS, doc="each interior voxel gets `per_axis^3` particles"
    )


@dataclass(frozen=True)
class MaterialConfig:
    """``type`` is a registry material, or "query" to ask the material query first."""

    type: str = setting(kind="other", doc="a registry name or alias (case-insensitive), or `query`")
    parameters: dict[str, float] = setting(
        kind="mapping",
        shown="registry defaults",
        doc="registry names in SI units; unknown names and values outside the valid range are errors",
    )
    density: float | None = setting(  # None only for "query" without a given density
        kind="number",
        unit="kg/m^3",
        low=DENSITY.valid[0],  # the registry's range, checked by DENSITY
        high=DENSITY.valid[1],
        shown="the material's",
        doc="the material's density",
    )
    model: str | None = setting(
        None,
        kind="other",
        shown="see below",
        doc="only for `elastic` (`fixed_corotated` by default, `neo_hookean`) and `sand` (`drucker_prager` by "
        "default, `volume_corrected`)",
    )
    query_image: Path | None = setting(
        None,
        kind="file",
        key="query.image",
        doc="an image file; at most one of `image` and `result`. With neither, the query looks at the object in "
        "the guidance video's first frame (written as `output/guidance_frame0.png`): the pixel box of its "
        "Gaussians' centres seen by the guidance camera, widened by a tenth of its size on each side (each of "
        "several objects its own box; the record's `crop_box`). Needs the video to be there already, at the "
        "camera's size",
    )
    query_result: Path | None = setting(  # read instead of asking
        None, kind="file", key="query.result", doc="a record file from `clflow query`"
    )
    query_prompt: str = setting("", kind="text", key="query.prompt", doc="text passed to the query")
    query_backend: str = setting(
        "offline", kind="choice", key="query.backend", choices=("offline", "openai"), doc="the query's backend"
    )


SINGLE_OBJECT = "object"  # the name of the one object of the single-object form (object + material)


@dataclass(frozen=True)
class SceneObject:
    """One simulated object: which Gaussians (``selection``), the particles filling it, its
    initial velocity (m/s, simulation frame) and its material. ``name`` names it in ``--set``
    keys (``objects.NAME.material.parameters.youngs_modulus``), in messages and in the
    outputs; ``key`` is where the config gives it: ``object`` (the single-object form, its
    material under ``material``) or ``objects.NAME``."""

    name: str
    selection: Selection
    fill: FillSettings
    material: MaterialConfig
    velocity: tuple[float, float, float] = setting(
        (0.0, 0.0, 0.0),
        kind="vec3",
        unit="m/s",
        high=SPEED,
        doc="in the simulation frame (like forces and gravity): every particle's initial velocity",
    )
    key: str = SINGLE_OBJECT

    @property
    def material_key(self) -> str:
        """The config key of its material: ``material`` or ``objects.NAME.material``."""
        return "material" if self.key == SINGLE_OBJECT else f"{self.key}.material"

    def own_file(self, stem: str, suffix: str) -> str:
        """The name of a file of its own in an output folder: STEM.SUFFIX for the object of
        the single-object form, STEM.NAME.SUFFIX for one of several."""
        return f"{stem}{suffix}" if self.key == SINGLE_OBJECT else f"{stem}.{self.name}{suffix}"


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
    """A half-space {x : (x - point) . normal < 0}, active during [start, end) s."""

    point: tuple[float, float, float] = setting(kind="vec3", unit="m", high=LENGTH, doc="a point on the plane")
    normal: tuple[float, float, float] = setting(
        kind="vec3", high=1e6, doc="of length >= 1e-6 (normalised): points into the free side"
    )
    mode: str = setting(
        "slip",
        kind="choice",
        choices=COLLIDER_MODES,
        doc="`sticky` (v = 0), `slip` (no normal velocity), `separate` (may leave the surface)",
    )
    friction: float = setting(
        0.0,
        kind="number",
        low=0.0,
        doc="Coulomb coefficient for slip and separate, acting while the material moves into the boundary",
    )
    start: float = setting(0.0, kind="number", unit="s", low=0.0, doc="active from")
    end: float = setting(math.inf, kind="number", unit="s", shown="never", doc="> `start`: active until")


DEFAULT_MAX_SUBSTEPS = 2000  # substeps per frame: beyond, a run is refused (docs/pipeline.md, pre-flight)


# a corner of simulation.domain: both are required where the domain is given
_DOMAIN_CORNER = {"kind": "vec3", "required": True, "unit": "m", "high": LENGTH, "shown": "around the object"}


@dataclass(frozen=True)
class SimulationSettings:
    grid_resolution: int = setting(
        32,
        kind="integer",
        low=11,
        high=MAX_GRID,
        doc="nodes along the domain's longest side (the walls take 4 cells a side; the device's memory refuses "
        "far fewer *(run)*)",
    )
    domain_lower: tuple[float, float, float] | None = setting(  # None: around the object
        None, key="domain.min", doc="the domain's lower corner, below `max` on every axis", **_DOMAIN_CORNER
    )
    domain_upper: tuple[float, float, float] | None = setting(
        None, key="domain.max", doc="its upper corner", **_DOMAIN_CORNER
    )
    substep_dt: float | None = setting(  # None: automatic (CFL, elastic wave speed, viscosity)
        None, kind="number", unit="s", low=1e-9, shown="`auto`", doc="`auto` (the stable step) or a fixed substep"
    )
    flip: float = setting(  # clflow.mpm.Simulator
        0.0,
        kind="number",
        low=0.0,
        high=1.0,
        doc="the PIC/FLIP blend of the particle velocities (0: APIC, whose damping grows with the substep count; "
        'docs/mpm.md, "Transfers and time step"). For identification 0.99 is recommended: the identification '
        "benchmark uses it, since with APIC a stiffer guess is also a more damped one",
    )
    fps: float = setting(
        24.0,
        kind="number",
        low=FPS[0],
        high=FPS[1],
        doc="frames per second of the output and of the guidance video",
    )
    frames: int = setting(24, kind="integer", low=1, doc="frames simulated after the rest state")
    gravity: tuple[float, float, float] = setting(
        (0.0, -9.81, 0.0), kind="vec3", unit="m/s^2", high=ACCELERATION, doc="the acceleration of gravity"
    )
    max_substeps: int = setting(
        DEFAULT_MAX_SUBSTEPS,
        kind="integer",
        low=1,
        doc="`optimize` and `simulate` refuse a run needing more substeps per frame *(run)*; `--max-substeps N` "
        "overrides it",
    )


_SCENE_VECTOR = {"kind": "vec3", "high": SCENE_LENGTH}  # a point or direction in the splat file's frame


@dataclass(frozen=True)
class CameraConfig:
    """A camera from a 3DGS cameras.json / NeRF transforms.json entry, from an image of a
    COLMAP sparse model (by name, or ``index`` in name order), or explicit."""

    cameras_file: Path | None = setting(
        None, kind="file", key="file", doc="a 3DGS `cameras.json` (a JSON list) or a NeRF `transforms.json`"
    )
    index: int = setting(
        0,
        kind="integer",
        low=0,
        doc="< the number of cameras in `file` (or of images in `colmap`, in name order) *(run)*",
    )
    colmap: Path | None = setting(
        None,
        kind="file",
        folder_ok=True,
        doc="a COLMAP sparse model folder (e.g. `sparse/0`: `cameras` and `images` as `.bin` or `.txt`, read as "
        "`clflow reconstruct` reads them); pinhole cameras only (undistort first)",
    )
    image: str | None = setting(
        None,
        kind="text",
        doc="with `colmap`: the name of the image whose camera is the guidance camera (as in `images.txt`) *(run)*",
    )
    position: tuple[float, float, float] | None = setting(
        None, unit="scene units", doc="the eye; required without `file`", **_SCENE_VECTOR
    )
    look_at: tuple[float, float, float] | None = setting(
        None, unit="scene units", doc="the point at the image centre; required without `file`", **_SCENE_VECTOR
    )
    up: tuple[float, float, float] = setting(
        (0.0, 1.0, 0.0), unit="scene axes", doc="the camera's up (use `[0, 0, 1]` for a z-up file)", **_SCENE_VECTOR
    )
    fov_y_deg: float = setting(50.0, kind="number", unit="deg", low=1.0, high=179.0, doc="the vertical field of view")
    width: int = setting(512, kind="integer", unit="px", low=8, high=MAX_PIXELS, doc="the image's width")
    height: int = setting(512, kind="integer", unit="px", low=8, high=MAX_PIXELS, doc="the image's height")


@dataclass(frozen=True)
class GuidanceView:
    """A further guidance view (``camera`` and ``video`` given as lists): its camera and video."""

    camera: CameraConfig
    video: Path | None


@dataclass(frozen=True)
class GenerateSettings:
    """``video: {generate: ...}``: make the guidance video with an image-to-video model first
    (clflow.pipeline.generated_video; None values: the model's or the scene's defaults)."""

    model: Path = setting(  # clflow.generate.inspect_model
        kind="other",
        doc="a local diffusers folder: CogVideoX image-to-video or Stable Video Diffusion (never downloaded)",
    )
    prompt: str | None = setting(  # None: the motion prompt filled from the forces (prompt_template)
        None, kind="text", shown="from the forces", doc="the motion prompt (CogVideoX; SVD takes none); non-empty"
    )
    prompt_template: str | None = setting(  # None: clflow.scene.video_settings.PROMPT_TEMPLATE
        None,
        kind="text",
        shown="see docs/generate.md",
        doc="the prompt made from the forces: placeholders `{object}`, `{motion}`, `{material}`",
    )
    object: str = setting("object", kind="text", doc="what the object is, for the template (`jelly cube`)")
    negative_prompt: str = setting("", kind="text", shown="empty", doc="what not to show (CogVideoX)")
    image: Path | None = setting(  # None: the scene rendered from the guidance camera
        None,
        kind="file",
        shown="the rendered scene",
        doc="the model's input image instead: the guidance camera's size",
    )
    seed: int = setting(0, kind="integer", low=0, doc="the same seed gives the same video")
    frames: int | None = setting(  # None: enough for the simulated time, as the model makes them
        None,
        kind="integer",
        low=2,
        high=10_000,
        shown="enough for the simulation",
        doc="a count the model makes (CogVideoX: 1 + 8k); must cover `simulation.frames / simulation.fps` s at `fps`",
    )
    fps: float | None = setting(
        None, kind="number", low=FPS[0], high=FPS[1], shown="`simulation.fps`", doc="the video's frame rate"
    )
    steps: int | None = setting(
        None, kind="integer", low=1, high=10_000, shown="the model's (50, SVD 25)", doc="denoising steps"
    )
    guidance_scale: float | None = setting(
        None,
        kind="number",
        low=0.0,
        high=1e3,
        shown="the model's (6, SVD 3)",
        doc="classifier-free guidance (SVD >= 1)",
    )
    size: tuple[int, int] | None = setting(  # (width, height) the model generates at
        None,
        kind="other",
        shown="the model's",
        doc=f"`WIDTHxHEIGHT` or `[width, height]` the model generates at, at most {MAX_PIXELS} a side; the image "
        "is scaled into it and the frames back to the camera's size",
    )
    fit: str = setting(
        "pad",
        kind="choice",
        choices=("pad", "crop"),
        doc="`pad` (the whole image, padded with its edge pixels) or `crop` (the frame filled)",
    )
    cpu_offload: bool = setting(False, kind="flag", doc="diffusers' model CPU offload (GPU runs)")
    vae_tiling: bool = setting(False, kind="flag", doc="diffusers' VAE tiling (CogVideoX)")
    vae_slicing: bool = setting(False, kind="flag", doc="diffusers' VAE slicing (CogVideoX)")


@dataclass(frozen=True)
class FlowSettings:
    """``flow``: the optical-flow estimator, the loss, its mask, confidence and bias correction."""

    method: str = setting("dis", kind="choice", choices=FLOW_METHODS, doc="the optical-flow estimator")
    preset: str = setting(
        DEFAULT_PRESET,
        kind="choice",
        choices=DIS_PRESETS,
        doc="DIS preset: OpenCV's `ultrafast`, `fast`, `medium` (finest level at 1/4, 1/4, 1/2 of the image size) "
        "or `fine` (medium down to full resolution)",
    )
    loss: str = setting(
        "l2",
        kind="choice",
        choices=FLOW_LOSSES,
        doc="`l2` (squared endpoint error, px^2) or `charbonnier` (robust, px)",
    )
    mask: str = setting(  # "alpha" (rendered object alpha at frame 0), "none", or a file
        "alpha",
        kind="other",
        doc="`alpha`, `none`, or a mask image file (its size must be the video's *(run)*)",
    )
    confidence: str = setting(  # per-pixel weight of the observed flow in the loss
        DEFAULT_CONFIDENCE,
        kind="choice",
        choices=CONFIDENCES,
        doc="`none` (every pixel of the mask counts fully) or `forward_backward` (each pixel weighted by the "
        "forward-backward consistency of the observed flow, 0 where it leaves the frame)",
    )
    stabilise: str = setting(
        "static",
        kind="choice",
        choices=STABILISATIONS,
        doc="`static` (each guidance frame registered to the first's camera and exposure over the pixels outside "
        "the objects before the flow: a shaking camera's motion and a flickering exposure taken out; a steady, "
        'evenly lit video is left as it is; docs/flow.md, "Stabilising the guidance") or `none`',
    )
    bias_correction: str = setting(  # the estimator's error on the simulation, subtracted
        DEFAULT_BIAS_CORRECTION,
        kind="choice",
        choices=BIAS_CORRECTIONS,
        doc="`none` (fit the observed flow as it is) or `simulated` (the optimiser renders its own simulation, "
        "runs the same estimator on it and subtracts the estimator's error from the observed flow: docs/flow.md, "
        '"Correcting the estimator\'s bias")',
    )


def main_grid_range(optimize: OptimizeSettings, simulation: SimulationSettings) -> tuple[int, int]:
    """The coarsest and finest main grid (nodes) a budget chooses from: the search's grid
    (the simulation's without one) up to ``budget.max_grid_resolution`` (0: twice the
    simulation's grid, in cells)."""
    search = optimize.search.grid_resolution if optimize.search is not None else 0
    lowest = search or simulation.grid_resolution
    finest = optimize.budget.max_grid_resolution if optimize.budget is not None else 0
    return lowest, max(lowest, finest or 2 * (simulation.grid_resolution - 1) + 1)


@dataclass(frozen=True)
class SceneConfig:
    source: Path
    splats: Path
    scale: float
    up: str
    objects: tuple[SceneObject, ...]  # one or more, in the config's order; their Gaussians do not overlap
    forces: tuple[ForceStage, ...]
    colliders: tuple[Collider, ...]
    simulation: SimulationSettings
    camera: CameraConfig
    video: Path | None
    flow: FlowSettings
    optimize: OptimizeSettings
    output: Path
    ground_truth: dict[str, float] = field(default_factory=dict)  # for metrics (RE) only; velocity as components
    more_views: tuple[GuidanceView, ...] = ()  # views 1.. when camera and video are lists; view 0 is camera, video
    generate: GenerateSettings | None = None  # video: {generate: ...}; video is None until it is made
    dataparser_transforms: Path | None = None  # nerfstudio's: camera files' frame -> the splat file's

    @property
    def object_names(self) -> tuple[str, ...]:
        return tuple(o.name for o in self.objects)

    @property
    def objects_word(self) -> str:
        """How a message calls the config's objects: "object" (one) or "objects"."""
        return "object" if len(self.objects) == 1 else "objects"

    @property
    def objects_label(self) -> str:
        """How a log line names them: "object", or "2 objects (jelly, heap)"."""
        names = ", ".join(self.object_names)
        return self.objects_word if len(self.objects) == 1 else f"{len(self.objects)} objects ({names})"

    def with_objects(self, objects) -> SceneConfig:
        """The config with ``objects`` (a sequence of SceneObject) instead of its own."""
        return replace(self, objects=tuple(objects))


def velocity_names(objects, k: int) -> tuple[str, tuple[str, str, str]]:
    """Object ``k``'s initial velocity as ``optimize.parameters`` and ``evaluation.ground_truth``
    name it, and its z components (m/s, scene axes): velocity and VELOCITY_COMPONENTS for the
    one object, OBJECT.velocity and OBJECT.velocity_x, ... with several."""
    return object_name(objects, k, VELOCITY), tuple(object_name(objects, k, c) for c in VELOCITY_COMPONENTS)


def object_name(objects, k: int, name: str, separator: str = ".") -> str:
    """``name`` (a parameter, a material) as records name object ``k``'s: bare for the one
    object, ``OBJECT<separator>name`` with several (``jelly.velocity``)."""
    return name if len(objects) == 1 else f"{objects[k].name}{separator}{name}"


def is_velocity_component(name: str) -> bool:
    """Whether the z name ``name`` is a velocity component (velocity_x, jelly.velocity_x)."""
    return name.rpartition(".")[2] in VELOCITY_COMPONENTS


def split_parameter(objects, name: str) -> tuple[int, str]:
    """(index into ``objects``, parameter) of a name of ``optimize.parameters`` or
    ``evaluation.ground_truth``: the bare parameter of the one object, ``OBJECT.PARAM`` with
    several (``jelly.youngs_modulus``); ValueError for an object that is not there."""
    if len(objects) == 1:
        return 0, name
    obj, _, param = name.partition(".")
    names = [o.name for o in objects]
    if obj not in names or not param:
        raise ValueError(f"{name!r} names none of the objects {', '.join(names)} (OBJECT.PARAM)")
    return names.index(obj), param


def objects_form(objects: tuple[SceneObject, ...], entries: list[dict]) -> dict:
    """``entries`` (one dict per object of ``objects``) as a record writes them, in the form
    of the config: the one object's keys at the top; with several ``{"objects": {name: entry}}``."""
    if len(objects) == 1:
        return dict(entries[0])
    return {"objects": {o.name: entry for o, entry in zip(objects, entries)}}


def object_entries(objects: tuple[SceneObject, ...], record) -> list:
    """Each object's entry of ``record``, a record written in the form of the config
    (:func:`objects_form`); ValueError when the record's form is not the config's or it
    lacks one of the objects."""
    several = isinstance(record, dict) and "objects" in record
    if several != (len(objects) > 1):
        what = "several objects" if several else "one object"
        raise ValueError(f"holds the parameters of {what}; the config simulates {len(objects)}")
    if not several:
        return [record]
    entries = record["objects"]
    missing = [o.name for o in objects if not isinstance(entries, dict) or not isinstance(entries.get(o.name), dict)]
    if missing:
        listed = ", ".join(entries) if isinstance(entries, dict) else "none"
        raise ValueError(f"lacks the object {missing[0]!r} of the config (it lists {listed})")
    return [entries[o.name] for o in objects]


def config_record(cfg: SceneConfig) -> dict:
    """``dataclasses.asdict`` of ``cfg`` for the records (run.json, a checkpoint's config
    digests): a config of one object keeps the keys it had before configs held several
    (selection, fill, material, velocity at the top; optimize.materials its object's list;
    no optimize.estimate_velocity_objects, the one object's name), so older records still
    compare; one of several has ``objects``."""
    from dataclasses import asdict

    fields = asdict(cfg)
    objects = fields.pop("objects")
    if len(objects) == 1:
        fields.update({key: objects[0][key] for key in ("selection", "fill", "material", "velocity")})
        fields["optimize"]["materials"] = next(iter(fields["optimize"]["materials"].values()), ())
        fields["optimize"]["estimate_velocity_objects"] = ()
    else:
        fields["objects"] = objects
    return fields


__all__ = [
    "CameraConfig",
    "Collider",
    "DEFAULT_MAX_SUBSTEPS",
    "FLOW_LOSSES",
    "FLOW_METHODS",
    "STABILISATIONS",
    "FillSettings",
    "FlowSettings",
    "ForceStage",
    "GenerateSettings",
    "GuidanceView",
    "MATERIAL_MODELS",
    "MaterialConfig",
    "SINGLE_OBJECT",
    "SceneConfig",
    "SceneObject",
    "Selection",
    "SimulationSettings",
    "UP_AXES",
    "config_record",
    "object_entries",
    "object_name",
    "objects_form",
    "is_velocity_component",
    "main_grid_range",
    "split_parameter",
    "velocity_names",
]
