"""The pipeline's steps as whole runs: what ``clflow optimize``, ``clflow simulate`` (a scene
config, or particles) and ``clflow render4d`` do, for the CLI, ``clflow demo`` and
``clflow sweep`` alike.

The CLI only parses options and says how to show progress: ``echo(line)`` for results
(stdout), ``note(line)`` for progress lines (stderr) and ``bar(total, done)``, a context
manager yielding ``advance(row)``; the defaults show nothing. Ctrl-C during an optimisation
raises KeyboardInterrupt with a one-line message saying what was saved and how to resume.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import warnings
from pathlib import Path
from typing import Callable, ContextManager

from clflow.errors import InputError
from clflow.limits import DEFAULT_MAX_OUTPUT_GB

#: what an interrupted optimisation leaves in its output folder for --resume: the main
#: checkpoint, the search starts' polishes, the material hypotheses' searches, the main grid
#: a budget chose (a new run times the device again)
RESUMABLE = ("checkpoint.json", "starts", "hypotheses", "budget.json")
#: an optimisation's results, written at its end as one step (all of them or none)
RESULTS = (
    "params.json",
    "metrics.json",
    "history.json",
    "search.json",
    "loss.png",
    "comparison*.mp4",
    "run.json",
    "index.html",
)
#: a run's own entries in its output folder (glob patterns), which a new run (no --resume)
#: removes as one step before it writes anything: the folder never mixes two runs
RUN_ENTRIES = (*RESUMABLE, "hypotheses.json", *RESULTS)
#: what an optimisation keeps in its folder across runs, each checked against the config
#: where it is read: the observed flow, the estimator's error, the material query's record
#: and the guidance frame it was asked about
CACHES = ("observed_flow*.npz", "estimator_error.npz", "material_query*.json", "guidance_frame0.png")


#: a scene simulation's entries in its folder, and what clflow render4d derives from them
SIMULATION_ENTRIES = ("gaussians.npz", "frame_*.ply", "static*.ply", "guidance", "guidance.mp4", "render4d")
#: a particle simulation's entries in its folder
PARTICLE_ENTRIES = ("positions.npz", "preview", "preview.mp4")

log = logging.getLogger("clflow.simulate")  # the log lines of `clflow simulate PARTICLES`


def _silent(line: str) -> None:
    """The default ``echo`` / ``note``: show nothing."""


def read_params_record(path: str | Path, cfg):
    """The material parameters, density and initial velocity of an optimisation's
    ``params.json`` applied to ``cfg`` (a SceneConfig of the same material): returns the
    config with that velocity (m/s), the parameter overrides (SI; ``density`` in kg/m^3) and
    the substeps per frame the optimiser's final evaluation needed (1 where the record,
    older or of another frame rate, does not say). A record of several objects (its
    ``objects`` by name) goes into each object's material and velocity; no overrides then."""
    from clflow.fileio import read_json

    record = read_json(path, "params file", "expected the params.json clflow optimize writes")
    several = isinstance(record, dict) and "objects" in record
    if several != (len(cfg.objects) > 1):
        what = "several objects" if several else "one object"
        raise InputError(f"{path} holds the parameters of {what}; {cfg.source} simulates {len(cfg.objects)}")
    if several:
        objects = [_object_from_record(path, record["objects"], obj) for obj in cfg.objects]
        return cfg.with_objects(objects), {}, _record_substeps(path, record, cfg)
    missing = [key for key in ("parameters", "density") if not isinstance(record, dict) or key not in record]
    if missing:
        raise InputError(
            f"{path} lacks {' and '.join(repr(k) for k in missing)}: not a params.json of clflow optimize "
            f"(it writes parameters, density and velocity)"
        )
    velocity = _checked_material(path, record, cfg.object)
    overrides = {**record["parameters"], "density": record["density"]}
    return cfg.with_object(velocity=velocity), overrides, _record_substeps(path, record, cfg)


def _checked_material(path, record: dict, obj) -> tuple[float, float, float]:
    """Check one object's entry of a params.json (``record``: material, parameters, density,
    velocity) against the config's object ``obj`` before any work; returns its velocity (m/s)."""
    from clflow.materials import DENSITY, validate_params
    from clflow.scene.config.settings import SINGLE_OBJECT

    where = str(path) if obj.key == SINGLE_OBJECT else f"{path}: object {obj.name!r}"
    if not isinstance(record.get("parameters"), dict):
        raise InputError(f"{where}: 'parameters' is not a table of numbers")
    if record.get("material") != obj.material.type:
        raise InputError(f"{where} is for {record.get('material')!r}, the config simulates {obj.material.type!r}")
    validate_params(obj.material.type, record["parameters"], where)  # as the config's, before any work
    DENSITY.check(record["density"], where)
    velocity = record.get("velocity", list(obj.velocity))  # older records have none
    if not (
        isinstance(velocity, list)
        and len(velocity) == 3
        and all(isinstance(v, (int, float)) and math.isfinite(v) for v in velocity)
    ):
        raise InputError(f"{where}: velocity must be a list of 3 finite numbers (m/s), got {velocity!r}")
    return tuple(float(v) for v in velocity)


def _object_from_record(path, records, obj):
    """The config's object ``obj`` (a SceneObject) with its material parameters, density and
    velocity from ``records`` (params.json's ``objects``: name -> entry)."""
    record = records.get(obj.name) if isinstance(records, dict) else None
    if not isinstance(record, dict) or "density" not in record:
        listed = ", ".join(records) if isinstance(records, dict) else "none"
        raise InputError(f"{path} lacks the object {obj.name!r} of the config, or its density (it lists {listed})")
    velocity = _checked_material(path, record, obj)
    parameters = {**obj.material.parameters, **record["parameters"]}
    material = dataclasses.replace(obj.material, parameters=parameters, density=float(record["density"]))
    return dataclasses.replace(obj, material=material, velocity=velocity)


def _record_substeps(path, record: dict, cfg) -> int:
    """The substeps per frame of a params.json at the config's frame rate (1 if it does not say)."""
    substeps = record.get("substeps", 1)
    if not (isinstance(substeps, int) and substeps >= 1):
        raise InputError(f"{path}: substeps must be a whole number >= 1, got {substeps!r}")
    if record.get("fps", cfg.simulation.fps) != cfg.simulation.fps:  # the same time step at another frame rate
        substeps = max(1, math.ceil(substeps * record["fps"] / cfg.simulation.fps - 1e-9))
    return substeps


def input_files(cfg) -> list[Path]:
    """Every file or folder a scene config ``cfg`` reads (the config itself, the splats, the
    videos, masks, camera files ...): the Path values of its settings, at any depth, but its
    output folder."""
    found: list[Path] = []

    def visit(value, name: str = "") -> None:
        if isinstance(value, Path) and name != "output":
            found.append(value)
        elif dataclasses.is_dataclass(value):
            for field in dataclasses.fields(value):
                visit(getattr(value, field.name), field.name)
        elif isinstance(value, (list, tuple)):
            for item in value:
                visit(item, name)

    visit(cfg)
    return found


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
    scene = None
    if len(cfg.objects) > 1:
        scene = load_scene_objects(cfg, torch.float32)  # selections checked (empty, overlapping) before a query
    out = Path(out_dir) if out_dir else cfg.output / "simulation"
    check_output(out)
    with output_folder(out):  # this run's: other runs are refused, before any work
        cfg = resolve_material(cfg)
        overrides, min_substeps = {}, 1
        if params_file:
            cfg, overrides, min_substeps = read_params_record(params_file, cfg)
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
                overrides,
                prepared,
                max_substeps=max_substeps,
                on_frame=_frame_progress(advance),
                min_substeps=min_substeps,
            )
        if len(cfg.objects) == 1:
            echo(f"{result.x.shape[1]:,} particles of {cfg.material.type}, {frames} frames")
        else:
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
        objects = "object" if len(cfg.objects) == 1 else "objects"
        echo(
            f"wrote {out / 'gaussians.npz'} and {result.x.shape[0]} PLY frames ({out / ('frame_000' + suffix)} ...)"
            + (f" of the {objects}, the static scene in {out / ('static' + suffix)}" if object_only else "")
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


def format_row(row: dict | None) -> str:
    """One optimisation progress row as text: loss, parameters and seconds per iteration."""
    if not row:
        return ""
    params = " ".join(f"{name}={value:.4g}" for name, value in row["params"].items())
    loss = "failed" if row["loss"] is None else f"{row['loss']:.4g}"
    if row.get("rejected"):
        loss = f"rejected (trial {loss})"
    start = f"start {row['start'] + 1}: " if "start" in row else ""  # a polish: iterations counted per start
    return f"{start}loss {loss}  {params}  {row['seconds']:.1f} s/it"


@contextlib.contextmanager
def iteration_lines(total: int, done: int, note: Callable[[str], None]):
    """A ``bar`` that notes one line per iteration (log files, CI): ``iteration k/total: row``."""
    yield lambda row: note(f"iteration {row['iteration'] + 1}/{total}: {format_row(row)}")


def run_optimization(
    config_path: str | Path,
    resume: bool = False,
    iterations: int | None = None,
    output: str | Path | None = None,
    overrides: tuple[str, ...] = (),
    max_substeps: int | None = None,
    force_video: bool = False,
    *,
    echo: Callable[[str], None] = _silent,
    note: Callable[[str], None] = _silent,
    bar: Callable[[int, int], ContextManager[Callable[[dict], None]]] | None = None,
    parallel: dict | None = None,
    resume_with: str | None = None,
) -> dict:
    """Load the config (``overrides``: ``KEY=VALUE``), generate its guidance video if it asks
    for one, choose among its material hypotheses, optimise (``bar(total, done)``: the
    iterations' progress, default :func:`iteration_lines`), write the results, run.json and
    the report; returns the metrics. ``resume`` continues from output/checkpoint.json.
    ``parallel``: the material hypotheses' searches and the search starts' polishes run as
    Ray tasks (clflow.parallel.map_on_ray's keywords: address, cpus_per_task, resources,
    device), with the serial path's results. ``resume_with``: the command an interruption
    says continues the run (default: the ``clflow optimize ... --resume`` that does; the
    demo's is ``clflow demo --resume``)."""
    from clflow.scene.config import load_config

    if parallel is not None:
        from clflow.parallel import require_ray

        require_ray("drop --parallel")
    cfg = load_config(config_path, overrides)
    with contextlib.ExitStack() as stack:
        search = cfg.optimize.search
        if parallel is not None and (cfg.optimize.materials or search is not None and search.starts > 1):
            from clflow.parallel import ray_session

            stack.enter_context(ray_session(parallel.get("address")))  # one Ray for all of the run's tasks
        again = resume_with or resume_command(
            config_path, output, overrides, iterations, max_substeps, force_video, parallel
        )
        return _optimize_config(
            cfg, again, resume, iterations, output, max_substeps, force_video, echo, note, bar, parallel
        )


def resume_command(config_path, output, overrides, iterations, max_substeps, force_video, parallel) -> str:
    """The command line that continues an interrupted ``clflow optimize`` with the options it
    was started with (shell-quoted)."""
    import shlex

    words = ["clflow", "optimize", str(config_path), "--resume"]
    words += ["-o", str(output)] if output is not None else []
    for item in overrides:
        words += ["--set", item]
    words += ["--iterations", str(iterations)] if iterations is not None else []
    words += ["--max-substeps", str(max_substeps)] if max_substeps is not None else []
    words += ["--force-video"] if force_video else []
    words += ["--parallel"] if parallel is not None else []
    return shlex.join(words)


def _optimize_config(
    cfg, again, resume, iterations, output, max_substeps, force_video, echo, note, bar, parallel
) -> dict:
    """run_optimization's work once its config is loaded (``again``: the command that resumes it)."""
    import torch

    from clflow.fileio import output_folder
    from clflow.limits import check_output
    from clflow.mpm.substep import check_device
    from clflow.runtime import get_device

    check_device(get_device(), torch.float32, differentiable=True)  # before any work
    if iterations is not None:
        cfg = dataclasses.replace(cfg, optimize=dataclasses.replace(cfg.optimize, iterations=iterations))
    if output is not None:
        cfg = dataclasses.replace(cfg, output=Path(output).resolve())
    check_output(cfg.output)
    created = not cfg.output.exists()
    with output_folder(cfg.output):  # this run's: other runs are refused, before any work
        return _optimize_held(cfg, again, resume, max_substeps, force_video, created, echo, note, bar, parallel)


def _optimize_held(cfg, again, resume, max_substeps, force_video, created, echo, note, bar, parallel) -> dict:
    """_optimize_config's work once this run holds the output folder (``created``: by this run)."""
    from clflow.fileio import check_output_folder, discard_written, remove_entries
    from clflow.pipeline.fit import resampled_guidance
    from clflow.pipeline.fit.state import check_resume

    if resume and not any((cfg.output / saved).exists() for saved in RESUMABLE):
        raise InputError(
            f"--resume: {cfg.output} holds no interrupted run to continue (no checkpoint.json); "
            f"run without --resume to start one"
        )
    if max_substeps is not None:
        cfg = dataclasses.replace(cfg, simulation=dataclasses.replace(cfg.simulation, max_substeps=max_substeps))
    generated = getattr(cfg, "generate", None) is not None  # video: {generate: ...}, made in the run
    for video in [cfg.video, *(view.video for view in cfg.more_views)]:
        if video is not None or not generated:  # none, unreadable, short or gapped: before the scene and kernels
            resampled_guidance(cfg, video, cfg.simulation.frames)
    query = any(o.material.type == "query" for o in cfg.objects)
    rewritten = query or cfg.optimize.materials or generated  # by the run's first steps
    if resume and not rewritten and (cfg.output / "checkpoint.json").exists():
        check_resume(cfg.output / "checkpoint.json", cfg)  # a changed --set or video: before the scene is loaded
    # what it removes (a new run: the earlier one), replaces at the end or keeps as a cache is clflow's
    check_output_folder(cfg.output, (*(RESULTS if resume else RUN_ENTRIES), *CACHES), input_files(cfg))
    if not resume:
        earlier = remove_entries(cfg.output, RUN_ENTRIES)  # as one step
        if earlier:
            note(f"a new run in {cfg.output}: removing the earlier run's {', '.join(earlier)}")
    try:
        return _optimize_prepared(cfg, again, resume, force_video, echo, note, bar, parallel)
    except BaseException:  # a first run that fails before it saved anything leaves no folder behind
        kept = (*RESUMABLE, "generated")  # what a rerun continues from, or an expensive generated video
        if created and not any((cfg.output / saved).exists() for saved in kept):
            discard_written(cfg.output)
        raise


def _chosen_material(cfg, again: str, resume: bool, force_video: bool, note, parallel):
    """optimize.material's hypotheses searched (serially or on Ray), the best chosen: its
    config, its start and the hypotheses' record (clflow.pipeline.hypotheses)."""
    from clflow.pipeline.hypotheses import choose_material

    search = cfg.optimize.search

    def searched(material: str, row: dict) -> None:
        note(f"{material}: search {row['iteration'] + 1}/{search.samples + search.refine}: {format_row(row)}")

    search_all = {}
    if parallel is not None:
        from clflow.pipeline.hypotheses import hypotheses_on_ray

        search_all = {"search_all": hypotheses_on_ray(**parallel)}
    try:
        cfg, start, hypotheses = choose_material(
            cfg, resume=resume, progress=searched, force_video=force_video, **search_all
        )
    except KeyboardInterrupt:
        raise KeyboardInterrupt(
            f"interrupted while searching the material hypotheses (each saves its samples "
            f"in {cfg.output / 'hypotheses'}); continue with `{again}`"
        ) from None
    note(
        f"material: {hypotheses['chosen']} fits best (best search loss: "
        + ", ".join(
            f"{m} {r['loss']:.4g}" if "loss" in r else f"{m} failed" for m, r in hypotheses["hypotheses"].items()
        )
        + ")"
    )
    return cfg, start, hypotheses


def _echo_results(opt, state, metrics: dict, report: Path, echo, note) -> None:
    """The optimised values, the errors against the ground truth, rollbacks, warnings and where the results are."""
    from clflow.pipeline.fit import parameter_unit

    cfg = opt.cfg
    final = opt.values(state.z)
    echo("optimised: " + ", ".join(f"{n} = {v:.6g} {parameter_unit(cfg, n)}" for n, v in final.items()))
    if "relative_error" in metrics:
        echo(
            "relative error vs ground truth: "
            + ", ".join(f"{n} {100 * e:.2f}%" for n, e in metrics["relative_error"].items())
        )
    errors = metrics.get("velocity_error_m_s")  # m/s: a number, or one per OBJECT.velocity
    if errors is not None:
        for name, error in (errors if isinstance(errors, dict) else {"initial velocity": errors}).items():
            echo(f"{name} off by {error:.3g} m/s")
    if metrics.get("rollbacks"):
        note(f"{len(metrics['rollbacks'])} unstable or failed iterations were rolled back (metrics.json: rollbacks)")
    for warning in metrics.get("warnings", []):
        note(f"WARNING: {warning}; the result is likely wrong")
    echo(
        f"flow loss {metrics['flow_loss']:.4g}, end-point error {metrics['epe_px']:.3g} px, "
        f"{metrics['seconds_per_iteration']:.2f} s per iteration; results in {cfg.output} (open {report.name})"
    )


def _optimize_prepared(cfg, again, resume, force_video, echo, note, bar, parallel) -> dict:
    """_optimize_config's work once the output folder is checked and cleared of an earlier run."""
    from clflow.pipeline.fit import Optimization

    if getattr(cfg, "generate", None) is not None:  # video: {generate: ...}: the guidance video first
        from clflow.pipeline.generated_video import ensure_guidance_video

        cfg = ensure_guidance_video(
            cfg, progress=lambda step, total: note(f"generating the guidance video: step {step}/{total}")
        )
    start, hypotheses, search = None, None, cfg.optimize.search
    if cfg.optimize.materials:  # material hypotheses: search each, optimise the best
        cfg, start, hypotheses = _chosen_material(cfg, again, resume, force_video, note, parallel)
    opt = Optimization(
        cfg, hypotheses=hypotheses, force_video=force_video
    )  # loads the scene, runs the material query, computes the video's flow
    if parallel is not None:
        from clflow.pipeline.fit import starts_on_ray

        opt.map_starts = starts_on_ray(**parallel)
    total = opt.total_iterations  # the velocity phase's (optimize.estimate_velocity) and the main phase's
    done = opt.load_state().iteration if resume and opt.checkpoint.exists() else 0
    with (bar or (lambda t, d: iteration_lines(t, d, note)))(total, done) as advance:

        def progress(row: dict) -> None:
            if row.get("phase") == "search":  # the global phase: one line per sample
                note(f"search {row['iteration'] + 1}/{search.samples + search.refine}: {format_row(row)}")
            else:
                advance(row)

        opt.progress = progress
        try:
            state = opt.run(resume=resume, start=start)
        except KeyboardInterrupt:  # (a new run cleared the earlier run's checkpoint before it began)
            if not opt.checkpoint.exists():
                raise KeyboardInterrupt("interrupted before the first iteration finished; nothing was saved") from None
            raise KeyboardInterrupt(
                f"interrupted after {opt.load_state().iteration} iterations (saved in {opt.checkpoint}); "
                f"continue with `{again}`"
            ) from None
    metrics = _write_results(opt, state, again, note)
    _echo_results(opt, state, metrics, cfg.output / "index.html", echo, note)
    return metrics


def _write_results(opt, state, again: str, note) -> dict:
    """The final evaluation (grid check, identifiability) and every result of RESULTS, as
    one step: an interruption or failure leaves the folder as it was (the checkpoint holds
    every iteration, so ``again`` only writes them)."""
    from clflow.fileio import atomic_dir
    from clflow.pipeline.report import write_report, write_run_record

    output = opt.cfg.output
    try:
        note("checking the result and writing it")
        with atomic_dir(output, replaces=RESULTS, inputs=input_files(opt.cfg)) as staged:
            metrics = opt.write_results(state, staged)
            write_run_record(opt.cfg, staged)
            write_report(output, staged)
    except KeyboardInterrupt:
        raise KeyboardInterrupt(
            f"interrupted while checking and writing the results, none of which were written; the "
            f"{state.iteration} iterations are saved in {opt.checkpoint}: write them with `{again}`"
        ) from None
    return metrics


__all__ = [
    "ParticleRun",
    "format_row",
    "iteration_lines",
    "read_params_record",
    "render_simulation_4d",
    "run_optimization",
    "simulate_particles",
    "simulate_scene",
]
