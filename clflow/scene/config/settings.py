"""The scene config's types, section by section, and the names and choices its keys take
(read and checked by clflow.scene.config.parse)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

from clflow.errors import InputError
from clflow.flow.optical_flow import (
    DEFAULT_BIAS_CORRECTION,
    DEFAULT_CONFIDENCE,
    DEFAULT_PRESET,
)
from clflow.mpm.material_model import ELASTIC_MODELS, SAND_MODELS
from clflow.regions import Region

UP_AXES = ("+x", "-x", "+y", "-y", "+z", "-z")
FLOW_METHODS = ("dis", "farneback")
FLOW_LOSSES = ("l2", "charbonnier")
MATERIAL_MODELS = {"elastic": ELASTIC_MODELS, "sand": SAND_MODELS}  # material.model options
VELOCITY = "velocity"  # the name of the object's initial velocity in optimize.parameters, evaluation.ground_truth
VELOCITY_COMPONENTS = ("velocity_x", "velocity_y", "velocity_z")  # its components: m/s, scene axes


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
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    key: str = SINGLE_OBJECT

    @property
    def material_key(self) -> str:
        """The config key of its material: ``material`` or ``objects.NAME.material``."""
        return "material" if self.key == SINGLE_OBJECT else f"{self.key}.material"


class SeveralObjectsError(InputError):
    """A step built for one object only asked a config of several for its object."""


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
    # with parameters of several objects, a round per object after the first: this many
    # samples per parameter of the object over its own box, the others held at the best so far
    object_samples: int = 12
    # nodes along the domain's longest side for the search and the starts' polish (0: the
    # simulation's): a coarser grid makes the global phase cheap, the main phase keeps the finer one
    grid_resolution: int = 0


@dataclass(frozen=True)
class BudgetSettings:
    """``optimize.budget``: the run's wall time, which chooses the main phase's grid from the
    device's measured speed (clflow.pipeline.fit.budget)."""

    seconds: float  # the whole optimisation: search, polishes, iterations, diagnostics
    # the finest main grid to consider (0: twice the simulation's); the coarsest is the search's
    max_grid_resolution: int = 0


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
    # several objects: the objects whose velocities the velocity phase estimates, by name
    estimate_velocity_objects: tuple[str, ...] = ()
    budget: BudgetSettings | None = None  # None: the main phase runs on simulation.grid_resolution

    def parameters_by_object(self) -> dict[str, tuple[str, ...]]:
        """Object name -> its optimised material parameters (OBJECT.PARAM), in the config's
        order, where they belong to two objects or more; else {} (the search's object rounds)."""
        if not all("." in name for name in self.parameters):
            return {}
        groups: dict[str, tuple[str, ...]] = {}
        for name in self.parameters:
            obj, _, param = name.partition(".")
            if param != VELOCITY:  # the search looks at material parameters only
                groups[obj] = groups.get(obj, ()) + (name,)
        return groups if len(groups) > 1 else {}

    def object_round_samples(self) -> int:
        """The samples of the search's object rounds, all objects together (0: none)."""
        if self.search is None:
            return 0
        return self.search.object_samples * sum(map(len, self.parameters_by_object().values()))


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
    def object(self) -> SceneObject:
        """The config's one object, for the steps built for one (optimisation, the guidance
        video's generation); SeveralObjectsError (one line) for a config of several."""
        if len(self.objects) != 1:
            names = ", ".join(o.name for o in self.objects)
            raise SeveralObjectsError(
                f"{self.source}: several objects ({names}): this step works on one object only for now"
            )
        return self.objects[0]

    # the one object's parts, as the single-object form gives them
    selection = property(lambda self: self.object.selection, doc="the one object's Selection")
    fill = property(lambda self: self.object.fill, doc="the one object's FillSettings")
    material = property(lambda self: self.object.material, doc="the one object's MaterialConfig")
    velocity = property(lambda self: self.object.velocity, doc="the one object's initial velocity, m/s")

    @property
    def object_names(self) -> tuple[str, ...]:
        return tuple(o.name for o in self.objects)

    def with_object(self, **changes) -> SceneConfig:
        """The config with the one object's fields changed (``material=``, ``velocity=``, ...)."""
        return replace(self, objects=(replace(self.object, **changes),))

    def with_objects(self, objects) -> SceneConfig:
        """The config with ``objects`` (a sequence of SceneObject) instead of its own."""
        return replace(self, objects=tuple(objects))


def velocity_names(objects, k: int) -> tuple[str, tuple[str, str, str]]:
    """Object ``k``'s initial velocity as ``optimize.parameters`` and ``evaluation.ground_truth``
    name it, and its z components (m/s, scene axes): velocity and VELOCITY_COMPONENTS for the
    one object, OBJECT.velocity and OBJECT.velocity_x, ... with several."""
    if len(objects) == 1:
        return VELOCITY, VELOCITY_COMPONENTS
    prefix = f"{objects[k].name}."
    return prefix + VELOCITY, tuple(prefix + c for c in VELOCITY_COMPONENTS)


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


def config_record(cfg: SceneConfig) -> dict:
    """``dataclasses.asdict`` of ``cfg`` for the records (run.json, a checkpoint's config
    digests): a config of one object keeps the keys it had before configs held several
    (selection, fill, material, velocity at the top), so older records still compare; one of
    several has ``objects``."""
    from dataclasses import asdict

    fields = asdict(cfg)
    objects = fields.pop("objects")
    if len(objects) == 1:
        fields.update({key: objects[0][key] for key in ("selection", "fill", "material", "velocity")})
    else:
        fields["objects"] = objects
    return fields


__all__ = [
    "BudgetSettings",
    "CameraConfig",
    "Collider",
    "DEFAULT_MAX_SUBSTEPS",
    "FLOW_LOSSES",
    "FLOW_METHODS",
    "FillSettings",
    "FlowSettings",
    "ForceStage",
    "GenerateSettings",
    "GuidanceView",
    "MATERIAL_MODELS",
    "MaterialConfig",
    "OPTIMIZERS",
    "OptimizeSettings",
    "SINGLE_OBJECT",
    "SceneConfig",
    "SceneObject",
    "SearchSettings",
    "SeveralObjectsError",
    "Selection",
    "SimulationSettings",
    "UP_AXES",
    "VELOCITY",
    "VELOCITY_COMPONENTS",
    "config_record",
    "is_velocity_component",
    "main_grid_range",
    "split_parameter",
    "velocity_names",
]
