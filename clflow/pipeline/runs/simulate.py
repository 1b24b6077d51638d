"""``clflow simulate`` (a scene config, or particles) and ``clflow render4d`` as whole runs."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import warnings
from pathlib import Path
from typing import Callable, ContextManager

from clflow.errors import InputError
from clflow.limits import DEFAULT_MAX_OUTPUT_GB
from clflow.pipeline.runs.progress import _silent
from clflow.pipeline.runs.records import input_files, read_params_record

#: a scene simulation's entries in its folder, and what clflow render4d derives from them
SIMULATION_ENTRIES = ("gaussians.npz", "frame_*.ply", "static*.ply", "guidance", "guidance.mp4", "render4d")
#: a particle simulation's entries in its folder
PARTICLE_ENTRIES = ("positions.npz", "preview", "preview.mp4")

log = logging.getLogger("clflow.simulate")  # the log lines of `clflow simulate PARTICLES`


def _frame_progress(advance) -> Callable[[int], None] | None:
    """A simulator's ``on_frame(k)`` that moves the progress to frame k: a run again after a
    CFL breach counts from its first frame, never past the total."""
    return (lambda k: advance(f"frame {k}", to=k)) if advance else None


def simulate_scene(
    config_path: str | Path,
    params_file: str | Path | None = None,
    out_dir: str | Path | None = None,
    preview: str = "mp4",
    max_output_gb: float = DEFAULT_MAX_OUTPUT_GB,
    settings: tuple[str, ...] = (),
    max_substeps: int | None = None,
    echo: Callable[[str], None] = _silent,
    object_only: bool = False,
    compressed: bool = False,
    progress: Callable[[int, str], ContextManager[Callable[[str], None]]] | None = None,
) -> Path:
    """Simulate the config's scene (``settings``: ``KEY=VALUE`` overrides) with its material
    and initial velocity, or those of an optimisation's ``params_file``; write per-frame
    Gaussians (``object_only``: PLY frames of the object and static.ply once; ``compressed``:
    as .compressed.ply) and, unless ``preview`` is "none", the guidance view ("mp4" or "png"
    frames) into ``out_dir`` (default: the config's output/simulation), all or nothing.
    ``max_substeps`` overrides ``simulation.max_substeps``; ``progress(total, label)`` yields
    ``advance(name, to=k)``, called after frame k (a CFL retry starts again at 1). Returns the folder."""
    import torch

    from clflow.fileio import atomic_dir, check_output_folder, output_folder
    from clflow.limits import check_memory, check_output
    from clflow.pipeline.forward import prepare, render_video, simulate_config
    from clflow.pipeline.frames4d import export_gaussians, export_size
    from clflow.pipeline.material import resolve_material
    from clflow.scene.config import load_config
    from clflow.scene.load import load_scene_objects

    cfg = load_config(config_path, settings)
    scene = load_scene_objects(cfg, torch.float32)  # selections checked (empty, overlapping) before a query
    out = Path(out_dir) if out_dir else cfg.output / "simulation"
    check_output(out)
    with output_folder(out):  # this run's: other runs are refused, before any work
        cfg = resolve_material(cfg)
        min_substeps = 1
        if params_file:
            cfg, min_substeps = read_params_record(params_file, cfg)
        inputs = [*input_files(cfg), *([params_file] if params_file else [])]
        check_output_folder(out, SIMULATION_ENTRIES, inputs, derived=True)
        prepared = prepare(cfg, scene=scene)
        frames = cfg.simulation.frames
        written, memory = export_size(prepared, frames, preview != "none")
        less = "simulate fewer frames (simulation.frames)"
        check_output(out, written, max_output_gb, f"{frames + 1:,} frames of Gaussians", less)
        check_memory(memory, f"simulating {frames + 1:,} frames", less)
        shown = progress(frames, "simulating") if progress else contextlib.nullcontext(None)
        with shown as advance:
            result = simulate_config(
                cfg,
                prepared=prepared,
                max_substeps=max_substeps,
                on_frame=_frame_progress(advance),
                min_substeps=min_substeps,
            )
        counts = torch.bincount(prepared.setup.object_index, minlength=len(cfg.objects)).tolist()
        each = ", ".join(f"{o.name} {c:,} of {o.material.type}" for o, c in zip(cfg.objects, counts))
        echo(f"{result.x.shape[1]:,} particles ({each}), {frames} frames")
        # all or nothing: a failure leaves OUT as it was; a success replaces the earlier
        # simulation's frames (all of them) and what was rendered from it
        with atomic_dir(out, replaces=SIMULATION_ENTRIES, inputs=inputs, derived=True) as tmp:
            export_gaussians(result, tmp, object_only, compressed)
            if preview != "none":
                render_video(result, tmp / "guidance", video=tmp / "guidance.mp4" if preview == "mp4" else None)
        suffix = ".compressed.ply" if compressed else ".ply"
        echo(
            f"wrote {out / 'gaussians.npz'} and {result.x.shape[0]} PLY frames ({out / ('frame_000' + suffix)} ...)"
            + (f" of the {cfg.objects_word}, the static scene in {out / ('static' + suffix)}" if object_only else "")
        )
        if preview != "none":
            echo(f"wrote {out / 'guidance.mp4' if preview == 'mp4' else out / 'guidance'}")
        return out


@dataclasses.dataclass(frozen=True)
class ParticleRun:
    """``clflow simulate`` without a scene config: particles (a file, or a built-in shape
    filling a cube of side ``size`` m centred at ``center``, default the domain's middle) of
    one material in a cubic domain of side ``domain`` m (origin at 0) with ``resolution``
    grid nodes per axis. SI units throughout; ``walls``: a collider mode or "none"."""

    particles: str | None = None
    shape: str = "box"
    size: float = 0.3
    center: tuple[float, float, float] | None = None
    material: str = "elastic"
    params: dict = dataclasses.field(default_factory=dict)
    model: str | None = None
    density: float | None = None
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    domain: float = 1.0
    resolution: int = 64
    particle_volume: float | None = None
    frames: int = 24
    fps: float = 24.0
    substeps: int | None = None
    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)
    walls: str = "separate"
    wall_friction: float = 0.0
    double: bool = False


def _particles_of(run: ParticleRun, dx: float):
    """The run's particles: x [N, 3] m and the volume per particle (m^3), from its file (volume:
    the file's, else ``particle_volume``, else (dx/2)^3) or its shape at 2 per cell and axis."""
    from clflow.mpm.shapes import lattice_fill, load_particles

    if run.particles:
        x, volume = load_particles(run.particles)
        if volume is not None and run.particle_volume is not None:
            raise InputError(f"{run.particles} gives each particle's 'volume': drop --particle-volume")
        if volume is None:
            volume = run.particle_volume if run.particle_volume is not None else (dx / 2) ** 3
            log.info("particle volume %.3g m^3 per particle (no 'volume' in %s)", volume, run.particles)
        return x, volume
    spacing = dx / 2  # 2 particles per cell and axis
    return lattice_fill(run.shape, run.size, list(run.center or [run.domain / 2] * 3), spacing), spacing**3


def _check_particle_outputs(out: Path, frames: int, n: int, itemsize: int, preview: str, max_output_gb: float):
    """Refuse a run whose trajectory (and preview) would not fit the disk or the memory."""
    from clflow.limits import TRAJECTORY_REALS, check_memory, check_output
    from clflow.mpm.preview import PREVIEW_SIZE

    less = "simulate fewer --frames"
    image = 0 if preview == "none" else 3 * PREVIEW_SIZE**2  # bytes of an uncompressed preview frame
    check_output(out, (frames + 1) * (12 * n + image), max_output_gb, f"{frames + 1:,} frames of {n:,} particles", less)
    check_memory(
        (frames + 1) * (n * TRAJECTORY_REALS * itemsize + image),  # the preview is encoded at once
        f"simulating {frames + 1:,} frames",
        less,
    )


def _run_with_cfl_retries(sim, simulator: Callable, frames: int, advance, chosen: bool, limit: int):
    """``sim.run(frames)``; on a CFL breach again at twice the substeps (``simulator(substeps)``
    makes the new one) up to ``limit``, unless the substeps were ``chosen`` by the user: then,
    and on any other failure, SimulationError with the way out (never a wrong result)."""
    from clflow.mpm import SimulationError

    while True:
        try:
            return sim.run(frames, _frame_progress(advance), strict_cfl=True)
        except SimulationError as exc:
            if "CFL" not in str(exc) or chosen or 2 * sim.substeps > limit:
                way_out = "more --substeps" if chosen else f"--max-substeps above {limit}"
                raise SimulationError(f"{exc}" + (f" ({way_out})" if "CFL" in str(exc) else "")) from None
            log.info("%s: simulating again at %d substeps per frame", exc, 2 * sim.substeps)
            sim = simulator(2 * sim.substeps)


def simulate_particles(
    run: ParticleRun,
    out_dir: str | Path = "simulation",
    preview: str = "mp4",
    max_output_gb: float = DEFAULT_MAX_OUTPUT_GB,
    max_substeps: int | None = None,
    device=None,
    echo: Callable[[str], None] = _silent,
    progress: Callable[[int, str], ContextManager[Callable[[str], None]]] | None = None,
) -> Path:
    """Simulate ``run`` on ``device`` (default: the selected one) and write
    OUT/positions.npz (x [frames+1, N, 3] m, time [frames+1] s) and a preview ("mp4",
    "png" frames or "none"), all or nothing; refuses more than ``max_substeps`` substeps per
    frame (default 2000); ``progress`` as :func:`simulate_scene`'s. Returns the folder."""
    import numpy as np
    import torch

    from clflow.fileio import atomic_dir, check_output_folder, output_folder
    from clflow.limits import check_output
    from clflow.mpm import Grid, MaterialSpec, Simulator, StabilityWarning
    from clflow.mpm.preview import PREVIEW_SIZE, write_preview
    from clflow.mpm.substep import check_device, check_grid_memory
    from clflow.pipeline.simulation import unstable_start
    from clflow.runtime import get_device
    from clflow.scene.config import DEFAULT_MAX_SUBSTEPS

    if run.resolution < 8 or not run.domain > 0:
        raise InputError(f"--grid must be >= 8 and --domain > 0, got {run.resolution}, {run.domain}")
    inputs = [run.particles] if run.particles else []
    check_output(out_dir)
    with output_folder(out_dir):  # this run's: other runs are refused, before any work
        check_output_folder(out_dir, PARTICLE_ENTRIES, inputs)
        dx = run.domain / (run.resolution - 1)
        grid = Grid((run.resolution,) * 3, dx)
        dtype = torch.float64 if run.double else torch.float32
        check_device(device or get_device(), dtype)
        check_grid_memory(device or get_device(), grid, dtype.itemsize)  # before filling the shape at dx / 2
        x, volume = _particles_of(run, dx)

        def simulator(substeps: int | None):
            return Simulator(
                x,
                volume,
                MaterialSpec(run.material, dict(run.params), run.density, run.model),
                grid,
                velocities=torch.tensor(run.velocity, dtype=torch.float64).expand(x.shape[0], 3),
                frame_dt=1.0 / run.fps,
                substeps=substeps,
                gravity=list(run.gravity),
                walls=None if run.walls == "none" else run.walls,
                wall_friction=run.wall_friction,
                dtype=dtype,
                device=device,
            )

        with warnings.catch_warnings():  # an unstable --substeps is refused below, with the option's name
            warnings.simplefilter("ignore", StabilityWarning)
            sim = simulator(run.substeps)
        unstable = run.substeps is not None and unstable_start(sim)
        if unstable:
            raise InputError(
                f"--substeps {run.substeps} (dt = {sim.dt:.3g} s) is {unstable}; the run would blow up or break the "
                f"CFL limit: use more --substeps, or leave the option out to take the stable count"
            )
        out, frames = Path(out_dir), run.frames
        _check_particle_outputs(out, frames, sim.n, dtype.itemsize, preview, max_output_gb)
        echo(
            f"{sim.n:,} particles of {run.material}, {frames} frames x {sim.substeps} substeps (dt = {sim.dt:.3g} s, "
            f"limited by {sim.limit_reason(sim.state.v)})"
        )
        limit = max_substeps or DEFAULT_MAX_SUBSTEPS
        if sim.substeps > limit:
            raise InputError(
                f"{sim.substeps} substeps per frame (dt = {sim.dt:.3g} s) is beyond the limit of {limit}; "
                f"ways out: a softer material, a coarser --grid, fewer --substeps, or raise the limit "
                f"with --max-substeps N"
            )
        shown = progress(frames, "simulating") if progress else contextlib.nullcontext(None)
        with shown as advance:
            traj = _run_with_cfl_retries(sim, simulator, frames, advance, chosen=run.substeps is not None, limit=limit)
        target = out / ("preview.mp4" if preview == "mp4" else "preview")
        with atomic_dir(out, replaces=PARTICLE_ENTRIES, inputs=inputs) as tmp:  # all or nothing, one result
            np.savez(tmp / "positions.npz", x=traj.x.float().numpy(), time=traj.time.numpy())
            if preview != "none":
                write_preview(traj.x, grid.origin, grid.upper, tmp / target.name, run.fps, PREVIEW_SIZE)
        echo(f"wrote {out / 'positions.npz'}")
        if preview != "none":
            echo(f"wrote {target}")
        return out


def render_simulation_4d(
    simulation: str | Path,
    out_dir: str | Path | None = None,
    views: int = 0,
    turns: float = 1.0,
    video_format: str = "mp4",
    max_output_gb: float = DEFAULT_MAX_OUTPUT_GB,
    progress: Callable[[int, str], ContextManager[Callable[[str], None]]] | None = None,
    echo: Callable[[str], None] = _silent,
) -> list[Path]:
    """Render the per-frame Gaussians ``simulate_scene`` wrote in ``simulation`` from the
    guidance camera, an orbiting camera and ``views`` fixed novel viewpoints into ``out_dir``
    (default: SIMULATION/render4d); ``progress(total, label)`` yields ``advance(name)``,
    called once per frame written. Returns the videos."""
    from clflow.fileio import check_output_folder, output_folder
    from clflow.limits import check_output
    from clflow.pipeline.frames4d import (
        NPZ_NAME,
        RENDER_4D_ENTRIES,
        load_frames,
        render_4d,
        render_4d_frames,
        render_4d_size,
    )

    simulation = Path(simulation)
    out = Path(out_dir) if out_dir else simulation / "render4d"
    with contextlib.ExitStack() as held:
        if simulation.is_dir():  # read while no run writes it
            held.enter_context(output_folder(simulation, shared=True))
        frames = load_frames(simulation)
        check_output(out)
        held.enter_context(output_folder(out))  # this run's: other runs are refused, before any work
        check_output_folder(out, RENDER_4D_ENTRIES, [simulation / NPZ_NAME])
        check_output(
            out,
            render_4d_size(frames, views),
            max_output_gb,
            f"{views + 2:,} sequences of {frames.frame_count} frames",
            "render fewer --views",
        )
        shown = progress(render_4d_frames(frames, views), "rendering") if progress else contextlib.nullcontext(None)
        with shown as advance:
            videos = render_4d(
                frames, out, views=views, turns=turns, video_format=video_format, advance=advance, source=simulation
            )
    for video in videos:
        echo(f"wrote {video} and {video.with_suffix('')}/*.png ({frames.frame_count} frames)")
    return videos


__all__ = [
    "PARTICLE_ENTRIES",
    "SIMULATION_ENTRIES",
    "ParticleRun",
    "render_simulation_4d",
    "simulate_particles",
    "simulate_scene",
]
