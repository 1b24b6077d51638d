"""Synthetic cases: a textured shape on a checkered floor, a material with ground-truth
parameters, forces (or a drop), a camera, and the guidance video rendered by clflow.

``make_case(folder, case, resolution)`` writes

- ``scene.ply``: procedural 3DGS Gaussians (metres, +y up): the shape's surface (flat
  Gaussians tangent to it; the pipeline fills the inside) and a static floor;
- ``config_truth.yaml``: the scene with the ground-truth material, simulated at
  ``truth_scale`` times the grid resolution (so its own, finer particle sampling and a
  smaller substep) and rendered at ``truth_scale`` times the image size;
- ``guidance/000.png ...`` and ``guidance.mp4``: the ground-truth simulation seen by the
  guidance camera, area-downsampled to the camera's size, with optional sensor noise
  (lossless PNG frames; ``codec`` makes the optimiser read a compressed video instead);
- ``config.yaml``: the same scene at the normal resolution starting from ``case.guess``
  with ``optimize`` set to recover ``case.optimize`` from the guidance video's optical flow;
- ``case.json``: how the guidance was made (resolutions, substeps, clamped particles).

A ``truth_scale`` above 1 keeps the benchmark honest: the optimiser cannot reproduce the
guidance exactly ("inverse crime"), as with a real video.

The bundled demo (datasets_tools/demo.py) is one case; benchmarks make others.
"""

from __future__ import annotations

import copy
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch

from clflow.scene.config import FlowSettings
from clflow_datasets.degradation import Degradation

SHAPES = ("cube", "sphere", "torus")
# bumped whenever make_case makes a case differently from the same SyntheticCase, so that
# results made before are not taken for results of the new cases (2: the ground GROUND_OFFSET
# cells above a node row at both the optimiser's and the truth's spacing; 3: exactly so, placed
# by clflow.pipeline.simulation for any grid over a configured domain; 4: Resolution.flip; 5:
# truths obey the CFL limit, run again at twice the substeps where they broke it)
GENERATOR_VERSION = 5


@dataclass(frozen=True)
class Resolution:
    """Detail knobs: ``object_detail`` sets the shape's Gaussian count (about
    6 x object_detail^2), ``floor_side`` floor Gaussians per side, image side (px), grid
    nodes along the domain's longest side, frames, optimisation iterations;
    ``main_grid_scale``: the optimiser's main phase runs on a grid this many times finer
    than ``grid``, on which its global phase runs (optimize.search.grid_resolution);
    ``flip``: the PIC/FLIP blend of the truth's and the optimiser's simulations
    (simulation.flip; 0 is APIC, whose damping grows with the substep count)."""

    object_detail: int = 14
    floor_side: int = 40
    image: int = 160
    grid: int = 24
    frames: int = 12
    iterations: int = 20
    main_grid_scale: float = 1.0
    flip: float = 0.0


@dataclass(frozen=True)
class SyntheticCase:
    """A shape (``size``: cube side, sphere diameter or torus outer diameter, m) resting on
    the floor or ``lift`` m above it, made of ``material`` with ``truth`` (SI), density in
    kg/m^3; ``guess`` is the optimisation's start for the ``optimize`` parameters.
    ``forces`` are config force stages (see docs/scene_config.md) in metres relative to the
    shape's centre; ``camera`` position and target likewise, in units of ``size``."""

    shape: str = "cube"
    size: float = 0.2
    lift: float = 0.0
    material: str = "elastic"
    truth: dict[str, float] = field(default_factory=lambda: {"youngs_modulus": 2.0e4, "poissons_ratio": 0.3})
    guess: dict[str, float] = field(default_factory=lambda: {"youngs_modulus": 2.0e3})
    density: float = 1000.0
    optimize: tuple[str, ...] = ("youngs_modulus",)
    learning_rate: float = 0.2  # per iteration, in the optimiser's z units (decades for moduli)
    horizon: tuple[int, int] = (4, 1)  # frames in the first iteration's loss, frames added per iteration
    search: int = 0  # samples of the optimiser's global phase (0: none)
    starts: int = 1  # the best samples polished by the local phase before the best is kept
    refine: int = 0  # second-round search samples around the best distinct samples (optimize.search.refine)
    method: str = "adam"  # the optimiser's local phase (optimize.method)
    forces: tuple[dict, ...] = ()
    ground: str = "sticky"
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)  # initial velocity (m/s, scene frame)
    spread: float | None = None  # room around the shape on each side (sizes); None: the default domain
    camera_offset: tuple[float, float, float] = (1.25, 1.75, 3.75)  # camera - centre, in sizes
    fov_y_deg: float = 40.0

    ROOM: ClassVar[str] = "SyntheticCase.spread"  # what gives a case more room

    def make_scene(self, folder: Path, resolution: Resolution, seed: int = 0) -> None:
        """Write its scene.ply into ``folder`` (:func:`write_scene`)."""
        write_scene(folder, self, resolution, seed)

    def make_config(
        self, resolution: Resolution, values: dict[str, float], optimize: bool, scale: int = 1, views: int = 1
    ) -> dict:
        """Its scene config with ``values`` (:func:`case_config`)."""
        return case_config(self, resolution, values, optimize, scale, views)

    @property
    def center(self) -> np.ndarray:
        """The shape's centre at rest (m)."""
        height = self.size * (0.25 if self.shape == "torus" else 0.5)  # a torus lies flat
        return np.array([0.0, self.lift + height, 0.0])


def _checker(u: np.ndarray, v: np.ndarray, cells: int, a, b) -> np.ndarray:
    """RGB [n, 3] of a checkerboard with ``cells`` squares per unit of (u, v) in [0, 1]."""
    odd = (np.floor(u * cells) + np.floor(v * cells)).astype(int) % 2 == 1
    return np.where(odd[:, None], np.asarray(b, float), np.asarray(a, float))


OBJECT_COLOURS = ((0.95, 0.35, 0.25), (0.98, 0.85, 0.3))


def cube_surface(side: float, centre, n: int, rng: np.random.Generator):
    """Gaussians on the 6 faces of a cube, n x n per face: means [6n^2, 3] m, scales
    [6n^2, 3] m, rotations [6n^2, 3, 3] (identity), rgb [6n^2, 3]."""
    means, scales, rgb = [], [], []
    grid = (np.arange(n) + 0.5) / n  # face coordinates in (0, 1)
    uu, vv = [a.ravel() for a in np.meshgrid(grid, grid, indexing="ij")]
    spacing = side / n
    for axis in range(3):
        for sign in (-1.0, 1.0):
            p = np.zeros((uu.size, 3))
            others = [a for a in range(3) if a != axis]
            p[:, others[0]] = (uu - 0.5) * side
            p[:, others[1]] = (vv - 0.5) * side
            p[:, axis] = sign * side / 2
            s = np.full((uu.size, 3), 0.6 * spacing)
            s[:, axis] = 0.1 * spacing  # flat along the face normal
            means.append(p + np.asarray(centre))
            scales.append(s)
            rgb.append(_checker(uu, vv, 4, *OBJECT_COLOURS))
    means, scales, rgb = np.concatenate(means), np.concatenate(scales), np.concatenate(rgb)
    rgb = rgb * (0.9 + 0.1 * rng.random((len(rgb), 1)))  # a little grain helps the flow
    return means, scales, np.broadcast_to(np.eye(3), (len(means), 3, 3)).copy(), rgb


def _tangent_frames(normals: np.ndarray) -> np.ndarray:
    """Rotations [n, 3, 3] whose third column is the unit normal (first two: a tangent basis)."""
    helper = np.where(np.abs(normals[:, 1:2]) < 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    t1 = np.cross(helper, normals)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    return np.stack([t1, t2, normals], axis=2)


def _flat_scales(count: int, area: float) -> np.ndarray:
    """Scales [count, 3] of flat Gaussians sharing ``area`` (m^2) evenly."""
    spacing = math.sqrt(area / count)
    return np.tile([0.7 * spacing, 0.7 * spacing, 0.1 * spacing], (count, 1))


def sphere_surface(diameter: float, centre, n: int, rng: np.random.Generator):
    """6 n^2 Gaussians on a sphere (Fibonacci lattice), flat along the normal."""
    count, r = 6 * n * n, diameter / 2
    k = np.arange(count) + 0.5
    polar, azimuth = np.arccos(1 - 2 * k / count), math.pi * (1 + 5**0.5) * k
    normals = np.stack([np.sin(polar) * np.cos(azimuth), np.cos(polar), np.sin(polar) * np.sin(azimuth)], 1)
    rgb = _checker((azimuth / (2 * math.pi)) % 1.0, polar / math.pi, 6, *OBJECT_COLOURS)
    rgb = rgb * (0.9 + 0.1 * rng.random((count, 1)))
    return (np.asarray(centre) + r * normals, _flat_scales(count, 4 * math.pi * r * r), _tangent_frames(normals), rgb)


def torus_surface(outer_diameter: float, centre, n: int, rng: np.random.Generator):
    """About 6 n^2 Gaussians on a torus lying flat (axis +y), tube radius = outer / 4."""
    a = outer_diameter / 4  # tube radius
    R = outer_diameter / 2 - a  # ring radius: R + a = outer / 2
    nu, nv = 3 * n, 2 * n
    u, v = [g.ravel() for g in np.meshgrid((np.arange(nu) + 0.5) / nu, (np.arange(nv) + 0.5) / nv, indexing="ij")]
    phi, theta = 2 * math.pi * u, 2 * math.pi * v
    ring = np.stack([np.cos(phi), np.zeros_like(phi), np.sin(phi)], 1)
    normals = np.cos(theta)[:, None] * ring + np.sin(theta)[:, None] * np.array([[0.0, 1.0, 0.0]])
    means = np.asarray(centre) + R * ring + a * normals
    # area element (R + a cos theta) dphi a dtheta: scale each Gaussian to its own patch
    patch = (2 * math.pi / nu) * (2 * math.pi * a / nv) * (R + a * np.cos(theta))
    spacing = np.sqrt(patch)[:, None]
    scales = np.concatenate([0.7 * spacing, 0.7 * spacing, 0.1 * spacing], 1)
    rgb = _checker(u, v, 6, *OBJECT_COLOURS) * (0.9 + 0.1 * rng.random((u.size, 1)))
    return means, scales, _tangent_frames(normals), rgb


SURFACES = {"cube": cube_surface, "sphere": sphere_surface, "torus": torus_surface}


def floor(size: float, n: int, height: float = 0.0):
    """Static floor Gaussians in the plane y = height: means, scales, rotations, rgb."""
    grid = (np.arange(n) + 0.5) / n
    uu, vv = [a.ravel() for a in np.meshgrid(grid, grid, indexing="ij")]
    means = np.stack([(uu - 0.5) * size, np.full(uu.size, height - 0.01), (vv - 0.5) * size], 1)
    spacing = size / n
    scales = np.tile([0.6 * spacing, 0.004, 0.6 * spacing], (uu.size, 1))
    rgb = _checker(uu, vv, 8, (0.85, 0.85, 0.85), (0.35, 0.4, 0.5))
    return means, scales, np.broadcast_to(np.eye(3), (uu.size, 3, 3)).copy(), rgb


def surface_gaussians(parts: list[tuple], opacity: float = 0.95):
    """Degree-0 float32 :class:`~clflow.splat.gaussians.Gaussians` of surface parts
    (means, scales, rotations, rgb arrays as the ``*_surface`` functions return), in order."""
    from clflow.splat.gaussians import Gaussians
    from clflow.splat.geometry import rotmat_to_quat
    from clflow.splat.sh import rgb_to_sh0

    means, scales, rotations, rgb = (torch.from_numpy(np.concatenate(arrays)) for arrays in zip(*parts))
    return Gaussians.from_activated(
        means.float(),
        rotmat_to_quat(rotations).float(),
        scales.float(),
        torch.full((means.shape[0],), opacity),
        sh=rgb_to_sh0(rgb.float())[:, None, :],
    )


def write_scene(folder: Path, case: SyntheticCase, resolution: Resolution, seed: int = 0) -> None:
    """Write the case's scene.ply: the shape's surface Gaussians, then the floor's."""
    from clflow.splat.ply import save_ply

    if case.shape not in SURFACES:
        raise ValueError(f"shape must be one of {', '.join(SHAPES)}, got {case.shape!r}")
    rng = np.random.default_rng(seed)
    parts = [
        SURFACES[case.shape](case.size, case.center, resolution.object_detail, rng),
        floor(6 * case.size, resolution.floor_side),
    ]
    save_ply(folder / "scene.ply", surface_gaussians(parts))


def push_upper_part(case_size: float = 0.2, acceleration: float = 12.0, duration: float = 0.12) -> dict:
    """A force stage that pushes the upper 40% of a shape resting on the floor along +x."""
    half = case_size
    return {
        "region": {"box": {"min": [-half, 0.1 * case_size, -half], "max": [half, half, half]}},
        "acceleration": [acceleration, 0.0, 0.0],
        "start": 0.0,
        "end": duration,
    }


def _rounded(values) -> list[float]:
    return [round(float(v), 9) for v in values]


def case_domain(case: SyntheticCase, resolution: Resolution, scale: int = 1) -> tuple[list[float], list[float], int]:
    """(domain min, domain max (m), grid nodes along its longest side) of a case with
    ``spread``: ``spread`` sizes of room around the shape on every horizontal side and half
    a size above it, besides the domain walls, at the grid spacing the default domain of
    ``resolution.grid`` nodes would have (2.5 sizes across), refined ``scale`` times
    (clflow.pipeline.simulation then moves it down by under a cell of whatever grid runs
    on it, to put the ground GROUND_OFFSET cells above a node row)."""
    from clflow.mpm.constants import WALL_CELLS
    from clflow.pipeline.simulation import GROUND_OFFSET

    s, c = case.size, case.center
    dx = 2.5 * s / (resolution.grid - 1)
    walls = (WALL_CELLS + 1) * dx  # the walls and the cell next to them are no room to move in
    room = case.spread * s + walls
    height = s / 4 if case.shape == "torus" else s / 2
    lower = [c[0] - s / 2 - room, -walls - GROUND_OFFSET * dx, c[2] - s / 2 - room]
    upper = [c[0] + s / 2 + room, c[1] + height + 0.5 * s + walls, c[2] + s / 2 + room]
    longest = max(u - lo for lo, u in zip(lower, upper))
    nodes = int(math.ceil(longest / dx - 1e-9)) + 1
    return _rounded(lower), _rounded(upper), (nodes - 1) * scale + 1


# guidance views of a case: view k circles the shape about +y by this azimuth from view 0
# (the second view looks across the first, where a single view sees depth worst)
VIEW_AZIMUTHS_DEG = (0.0, 90.0, -90.0, 180.0)


def case_camera(case: SyntheticCase, image: int, view: int = 0) -> dict:
    """Config camera of guidance view ``view`` (0 .. len(VIEW_AZIMUTHS_DEG) - 1), ``image`` px square."""
    c, s = case.center, case.size
    a = math.radians(VIEW_AZIMUTHS_DEG[view])
    x, y, z = case.camera_offset
    offset = np.array([x * math.cos(a) + z * math.sin(a), y, -x * math.sin(a) + z * math.cos(a)])
    return {
        "position": _rounded(c + s * offset),
        "look_at": _rounded(c),
        "fov_y_deg": case.fov_y_deg,
        "width": image,
        "height": image,
    }


def guidance_name(view: int) -> str:
    """The guidance frame folder of view ``view``."""
    return "guidance" if view == 0 else f"guidance_{view}"


def case_config(
    case: SyntheticCase,
    resolution: Resolution,
    parameters: dict[str, float],
    optimize: bool,
    scale: int = 1,
    views: int = 1,
) -> dict:
    """The case's scene config (as a dict; see clflow.scene.config); ``scale`` multiplies
    the grid resolution (nodes - 1) and the image size; ``views`` guidance cameras (and
    videos) as lists when more than one."""
    if not 1 <= views <= len(VIEW_AZIMUTHS_DEG):
        raise ValueError(f"views must be 1..{len(VIEW_AZIMUTHS_DEG)}, got {views}")
    c, s = case.center, case.size
    margin = 0.025 * s
    half = s / 2 + margin
    height = (s / 4 if case.shape == "torus" else s / 2) + margin
    forces = []
    for stage in case.forces:  # regions relative to the centre -> absolute
        stage = copy.deepcopy(stage)
        box = stage["region"].get("box")
        if box is not None:
            box["min"], box["max"] = _rounded(np.add(box["min"], c)), _rounded(np.add(box["max"], c))
        forces.append(stage)
    simulation = {"grid_resolution": (resolution.grid - 1) * scale + 1, "fps": 24, "frames": resolution.frames}
    if resolution.flip:
        simulation["flip"] = resolution.flip
    if case.spread is not None:
        lower, upper, nodes = case_domain(case, resolution, scale)
        simulation.update(grid_resolution=nodes, domain={"min": lower, "max": upper})
    obj = {
        "select": {
            "box": {
                "min": _rounded([c[0] - half, case.lift - margin, c[2] - half]),
                "max": _rounded([c[0] + half, c[1] + height, c[2] + half]),
            }
        }
    }
    if any(case.velocity):
        obj["velocity"] = _rounded(case.velocity)
    config = {
        "splats": "scene.ply",
        "scene": {"scale": 1.0, "up": "+y"},
        "object": obj,
        "material": {"type": case.material, "parameters": dict(parameters), "density": case.density},
        "forces": forces,
        "boundaries": {"ground": {"height": 0.0, "mode": case.ground}},
        "simulation": simulation,
        "camera": [case_camera(case, resolution.image * scale, v) for v in range(views)]
        if views > 1
        else case_camera(case, resolution.image * scale),
        "flow": asdict(FlowSettings()),  # the defaults, spelled out
        "output": "results",
    }
    if optimize:
        add_optimization(
            config, case, resolution, [guidance_name(v) for v in range(views)] if views > 1 else guidance_name(0)
        )
    return config


def add_optimization(config: dict, case, resolution: Resolution, video: str | list[str]) -> None:
    """Give a case's ``config`` (a dict) its ``video`` (the guidance's folder or folders) and
    the case's optimize and evaluation sections (``case``: a SyntheticCase or SceneCase); with
    a search and resolution.main_grid_scale != 1 the global phase keeps the config's grid and
    the main phase runs on one main_grid_scale times finer."""
    simulation = config["simulation"]
    coarse_search = bool(case.search) and resolution.main_grid_scale != 1
    if coarse_search:
        search_grid = simulation["grid_resolution"]
        simulation["grid_resolution"] = round((search_grid - 1) * resolution.main_grid_scale) + 1
    config["video"] = video
    config["optimize"] = {
        "parameters": list(case.optimize),
        "learning_rates": {n: case.learning_rate for n in case.optimize},
        "iterations": resolution.iterations,
        "horizon": {"start": case.horizon[0], "step": case.horizon[1]},
    }
    if case.search:
        search = {"samples": case.search}
        search.update({"starts": case.starts} if case.starts > 1 else {})
        search.update({"refine": case.refine} if case.refine else {})
        search.update({"grid_resolution": search_grid} if coarse_search else {})
        config["optimize"]["search"] = search
    if case.method != "adam":
        config["optimize"]["method"] = case.method
    config["evaluation"] = {"ground_truth": dict(case.truth)}


def wall_contacts(result) -> int:
    """Particle-frames of a simulation result (clflow.pipeline.forward.SimulationResult)
    inside the domain's wall cells or the cell next to them, where the walls, not the
    material, decide the motion."""
    from clflow.mpm.constants import WALL_CELLS

    grid = result.prepared.setup.grid
    reach = (WALL_CELLS + 1) * grid.dx
    lower = torch.tensor(grid.origin, dtype=result.x.dtype) + reach
    upper = torch.tensor(grid.upper, dtype=result.x.dtype) - reach
    return int(((result.x < lower) | (result.x > upper)).any(-1).sum())


def degrade(
    frames: np.ndarray,
    size: int,
    noise: float,
    rng: np.random.Generator,
    degradation: Degradation = Degradation(),
    artefact_rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Frames [T, H, W, 3] uint8 area-averaged down to [T, size, size, 3], with Gaussian
    sensor noise of ``noise`` grey levels (standard deviation, 8-bit scale, drawn from
    ``rng``) added and the artefacts of ``degradation`` (drawn from ``artefact_rng``; the
    order: clflow_datasets.degradation)."""
    out = degradation.apply(frames, size, artefact_rng or np.random.default_rng(0))
    if noise > 0:
        out += rng.normal(0.0, noise, out.shape)
    return degradation.encode(out)


CASE_FILES = ("scene.ply", "config_truth.yaml", "guidance", "guidance.mp4", "config.yaml", "case.json")
"""What :func:`make_case` writes into its folder (besides ``guidance_coded*`` with a codec,
and ``guidance_K*`` for further views)."""


def _write_guidance(
    folder: Path, result, truth_cfg, image: int, fps: float, noise: float, codec, seed: int, degradation: Degradation
):
    """Each view of the truth's ``result`` rendered, degraded to ``image`` px with ``noise`` and
    ``degradation``, as PNG frames and an MP4 at ``fps`` (and coded with ``codec``); returns
    the coded videos' names."""
    from clflow.media import write_image, write_video
    from clflow.pipeline.forward import render_frames
    from clflow.scene.load import guidance_camera

    cameras = [None] + [guidance_camera(truth_cfg, v.camera) for v in truth_cfg.more_views]
    coded = []
    for view, camera in enumerate(cameras):  # view 0's noise draws are those of a one-view case
        rngs = np.random.default_rng(seed + 1 + 1000 * view), np.random.default_rng([seed, view])
        frames = degrade(render_frames(result, camera), image, noise, rngs[0], degradation, rngs[1])
        name = guidance_name(view)
        (folder / name).mkdir(exist_ok=True)
        for t, frame in enumerate(frames):
            write_image(folder / name / f"{t:03d}.png", frame)
        write_video(folder / f"{name}.mp4", frames, fps)
        if codec is not None:
            write_video(folder / f"{name}_coded{codec}", frames, fps)
            coded.append(f"{name}_coded{codec}")
    return coded


def make_case(
    folder: str | Path,
    case,
    resolution: Resolution = Resolution(),
    seed: int = 0,
    *,
    truth_scale: int = 1,
    noise: float = 0.0,
    codec: str | None = None,
    views: int = 1,
    truth_flip: float | None = None,
    degradation: Degradation = Degradation(),
) -> Path:
    """Write the case (a :class:`SyntheticCase`, or a clflow_datasets.scene_cases.SceneCase
    of several objects, one view) into ``folder`` (see module docstring); returns its
    ``config.yaml``.

    ``truth_scale``: the ground truth's grid and image refinement (1: the optimiser's own
    resolution, an inverse crime; 2 for benchmarks); ``truth_flip``: the ground truth's PIC/FLIP
    blend (0: APIC; default the resolution's, the optimiser's own); ``noise``: sensor noise (8-bit grey
    levels); ``codec``: a video suffix (".mp4", ".webm", ...) whose lossy encoding the
    optimiser then reads instead of the PNG frames; ``views``: guidance views of the same
    motion (``guidance/``, ``guidance_1/`` ..., cameras at VIEW_AZIMUTHS_DEG); ``degradation``:
    what a generated or hand-held video adds (clflow_datasets.degradation; its ``speed``
    simulates the truth at that many times the video's frame interval). Raises
    ValueError if the ground-truth run clamps particles at the grid's edge (the domain is
    too small for the motion)."""
    import json

    import yaml

    from clflow.fileio import atomic_write_text
    from clflow.scene.config import parse_config

    if int(truth_scale) < 1:
        raise ValueError(f"truth_scale must be an integer >= 1, got {truth_scale}")
    if not noise >= 0:
        raise ValueError(f"noise must be >= 0 grey levels, got {noise}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    case.make_scene(folder, resolution, seed)
    # the truth's own transfer (truth_flip; default the optimiser's): nature is neither APIC nor FLIP
    truth_resolution = resolution if truth_flip is None else replace(resolution, flip=float(truth_flip))
    truth = case.make_config(truth_resolution, case.truth, optimize=False, scale=int(truth_scale), views=views)
    fps = truth["simulation"]["fps"]  # the video's; the truth's frames lie `speed` times its interval apart
    if degradation.speed != 1.0:
        truth["simulation"]["fps"] = fps / degradation.speed
    atomic_write_text(folder / "config_truth.yaml", yaml.safe_dump(truth, sort_keys=False))
    truth_cfg = parse_config(truth, str(folder / "config_truth.yaml"), folder)
    result = truth_run(folder, truth_cfg, case.ROOM)
    config = case.make_config(resolution, {**case.truth, **case.guess}, optimize=True, views=views)
    coded = _write_guidance(folder, result, truth_cfg, resolution.image, fps, noise, codec, seed, degradation)
    if coded:
        config["video"] = coded if views > 1 else coded[0]
    atomic_write_text(folder / "config.yaml", yaml.safe_dump(config, sort_keys=False))
    extra = {"noise": noise, "codec": codec, "seed": seed, "views": views}
    if degradation != Degradation():
        extra["degradation"] = asdict(degradation)
    record = case_record(truth, config, truth_cfg, result, resolution.image, truth_resolution.flip, extra)
    atomic_write_text(folder / "case.json", json.dumps(record, indent=2))
    return folder / "config.yaml"


def truth_run(folder: Path, truth_cfg, room: str):
    """The ground truth's simulation (clflow.pipeline.forward.SimulationResult) of
    ``truth_cfg``: ValueError if it clamps particles at the grid's edge or brings them into
    the domain's walls (``room``: what gives a case more room). A truth that breaks the CFL
    limit runs again at twice the substeps (as the optimiser's runs do), and is an error at
    simulation.max_substeps: never a truth from an unstable step."""
    from clflow.pipeline.forward import simulate_config

    result = simulate_config(truth_cfg)
    clamped, at_walls = int(result.clamped.sum()), wall_contacts(result)
    if clamped or at_walls:
        raise ValueError(
            f"{folder}: the ground-truth run clamped {clamped} particle-frames at the grid's edge and "
            f"brought {at_walls} particle-frames into the domain walls; give the case more room ({room})"
        )
    return result


def case_record(truth: dict, config: dict, truth_cfg, result, image: int, truth_flip: float, extra: dict) -> dict:
    """case.json: the truth's and the optimiser's grids, images, particles and substeps, and ``extra``."""
    return {
        "truth_grid_resolution": truth["simulation"]["grid_resolution"],
        "grid_resolution": config["simulation"]["grid_resolution"],
        "truth_image": truth_cfg.camera.width,
        "image": image,
        "truth_particles": int(result.x.shape[1]),
        "truth_substeps": result.substeps,
        "truth_flip": truth_flip,
        "clamped": int(result.clamped.sum()),
        "wall_contacts": 0,  # truth_run refuses any
        **extra,
    }


__all__ = [
    "GENERATOR_VERSION",
    "Resolution",
    "SHAPES",
    "SyntheticCase",
    "VIEW_AZIMUTHS_DEG",
    "case_camera",
    "case_config",
    "guidance_name",
    "case_domain",
    "cube_surface",
    "degrade",
    "wall_contacts",
    "floor",
    "make_case",
    "add_optimization",
    "CASE_FILES",
    "case_record",
    "truth_run",
    "push_upper_part",
    "sphere_surface",
    "surface_gaussians",
    "torus_surface",
    "write_scene",
]
