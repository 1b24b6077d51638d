"""``clflow simulate``: run the MLS-MPM simulator on a particle file or a built-in shape."""

import click

from clflow.limits import DEFAULT_MAX_OUTPUT_GB
from clflow_cli.main import max_output_option


def _vec3(text: str, what: str):
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3:
        raise click.BadParameter(f"{what} must be three comma-separated numbers, got {text!r}")
    return values


def _params(items):
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep:
            raise click.BadParameter(f"--param takes NAME=VALUE, got {item!r}")
        try:
            out[name.strip()] = float(value)
        except ValueError:
            raise click.BadParameter(f"--param {name}: {value!r} is not a number") from None
    return out


CONFIG_SUFFIXES = (".yaml", ".yml", ".json")


def simulate_scene(config_path: str, params_file: str | None, out_dir: str | None, preview: str,
                   max_output_gb: float = DEFAULT_MAX_OUTPUT_GB, settings: tuple[str, ...] = (),
                   max_substeps: int | None = None, object_only: bool = False, compressed: bool = False) -> None:
    """``clflow simulate CONFIG``: the config's scene (``settings``: ``--set KEY=VALUE``) with
    its material and initial velocity (or those of an optimisation's params.json), written as
    per-frame Gaussians (``object_only``: PLY frames of the object and static.ply once;
    ``compressed``: as .compressed.ply) and a guidance-view video; ``max_substeps``
    overrides the config's ``simulation.max_substeps``."""
    import dataclasses
    import json
    import math
    from pathlib import Path

    from clflow.errors import InputError
    from clflow.fileio import atomic_dir
    from clflow.limits import check_memory, check_output
    from clflow.pipeline.forward import prepare, render_video, simulate_config
    from clflow.pipeline.frames4d import export_gaussians, export_size
    from clflow.pipeline.material import resolve_material
    from clflow.scene.config import load_config

    cfg = resolve_material(load_config(config_path, settings))
    overrides = {}
    if params_file:
        try:
            record = json.loads(Path(params_file).read_text())
            overrides = {**record["parameters"], "density": record["density"]}
            velocity = record.get("velocity", list(cfg.velocity))  # older records have none
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise InputError(f"{params_file}: not a params.json of clflow optimize ({exc})") from None
        if record.get("material") != cfg.material.type:
            raise InputError(f"{params_file} is for {record.get('material')!r}, the config simulates {cfg.material.type!r}")
        if not (isinstance(velocity, list) and len(velocity) == 3
                and all(isinstance(v, (int, float)) and math.isfinite(v) for v in velocity)):
            raise InputError(f"{params_file}: velocity must be a list of 3 finite numbers (m/s), got {velocity!r}")
        cfg = dataclasses.replace(cfg, velocity=tuple(float(v) for v in velocity))  # the optimised one
    out = Path(out_dir) if out_dir else cfg.output / "simulation"
    prepared = prepare(cfg)
    frames = cfg.simulation.frames
    written, memory = export_size(prepared, frames, preview != "none")
    less = "simulate fewer frames (simulation.frames)"
    check_output(out, written, max_output_gb, f"{frames + 1:,} frames of Gaussians", less)
    check_memory(memory, f"simulating {frames + 1:,} frames", less)
    result = simulate_config(cfg, overrides, prepared, max_substeps=max_substeps or cfg.simulation.max_substeps)
    click.echo(f"{result.x.shape[1]:,} particles of {cfg.material.type}, {frames} frames")
    with atomic_dir(out) as tmp:  # all or nothing: a failure leaves OUT as it was
        export_gaussians(result, tmp, object_only, compressed)
        if preview != "none":
            render_video(result, tmp / "guidance", video=tmp / "guidance.mp4" if preview == "mp4" else None)
    suffix = ".compressed.ply" if compressed else ".ply"
    click.echo(f"wrote {out / 'gaussians.npz'} and {result.x.shape[0]} PLY frames ({out / ('frame_000' + suffix)} ...)"
               + (f" of the object, the static scene in {out / ('static' + suffix)}" if object_only else ""))
    if preview != "none":
        click.echo(f"wrote {out / 'guidance.mp4' if preview == 'mp4' else out / 'guidance'}")


@click.command("simulate")
@click.argument("particles", required=False, type=click.Path(dir_okay=False))
@click.option("--shape", type=click.Choice(["box", "sphere", "torus"]), default="box", show_default=True,
              help="Built-in shape when no particle file is given.")
@click.option("--size", default=0.3, show_default=True, help="Shape size (m): cube side, sphere or torus diameter.")
@click.option("--center", default=None, help="Shape centre 'x,y,z' (m); default: the middle of the domain.")
@click.option("--material", "-m", default="elastic", show_default=True, help="Material name (clflow.materials).")
@click.option("--param", "-p", "params", multiple=True, metavar="NAME=VALUE",
              help="Material parameter in SI units, e.g. -p youngs_modulus=2e5 (repeatable).")
@click.option("--model", default=None, help="Elastic model: fixed_corotated (default) or neo_hookean; sand: drucker_prager "
                                           "(default) or volume_corrected.")
@click.option("--density", type=float, default=None, help="Density (kg/m^3); default: the material's.")
@click.option("--velocity", default="0,0,0", show_default=True, help="Initial velocity 'vx,vy,vz' (m/s).")
@click.option("--domain", default=1.0, show_default=True, help="Side of the cubic domain (m), origin at 0.")
@click.option("--grid", "resolution", default=64, show_default=True, help="Grid nodes per axis.")
@click.option("--particle-volume", type=float, default=None,
              help="Rest volume per particle (m^3) for particle files without one; default (dx/2)^3.")
@click.option("--frames", default=24, show_default=True, help="Frames to simulate.")
@click.option("--fps", default=24.0, show_default=True, help="Frames per second.")
@click.option("--substeps", type=int, default=None, help="Substeps per frame (default: the stable count).")
@click.option("--gravity", default="0,-9.81,0", show_default=True, help="Gravity 'gx,gy,gz' (m/s^2).")
@click.option("--walls", type=click.Choice(["separate", "slip", "sticky", "none"]), default="separate",
              show_default=True, help="Domain-wall condition.")
@click.option("--wall-friction", default=0.0, show_default=True, help="Coulomb friction of the walls.")
@click.option("--double", is_flag=True, help="Simulate in float64.")
@click.option("--out", "-o", "out_dir", default=None, type=click.Path(file_okay=False),
              help="Output folder [default: simulation; for a config: its output/simulation].")
@click.option("--params", "params_file", type=click.Path(dir_okay=False),
              help="With a CONFIG: simulate with the parameters of this params.json (clflow optimize).")
@click.option("--preview", type=click.Choice(["mp4", "png", "none"]), default="mp4", show_default=True,
              help="Preview video, PNG frames, or none.")
@max_output_option
@click.option("--set", "overrides", multiple=True, metavar="KEY.SUB=VALUE",
              help="With a CONFIG: set a config key, the value read as YAML, e.g. --set simulation.frames=48 "
                   "(repeatable; checked like the file).")
@click.option("--max-substeps", type=click.IntRange(min=1), default=None,
              help="Refuse a run needing more substeps per frame [default: a config's simulation.max_substeps, "
                   "else 2000].")
@click.option("--object-only", is_flag=True,
              help="With a CONFIG: PLY frames of the object alone, the static Gaussians once in OUT/static.ply.")
@click.option("--compressed-ply", "compressed", is_flag=True,
              help="With a CONFIG: write the PLYs compressed (frame_000.compressed.ply ..., the format SuperSplat and "
                   "PlayCanvas read), about a quarter of the size.")
@click.pass_context
def simulate(ctx, particles, shape, size, center, material, params, model, density, velocity, domain, resolution,
             particle_volume, frames, fps, substeps, gravity, walls, wall_friction, double, out_dir, params_file,
             preview, max_output_gb, overrides, max_substeps, object_only, compressed):
    """Simulate PARTICLES (.npz with 'positions' [N, 3] in m and optional 'volume' [N] in
    m^3, or a .ply point cloud) or a built-in shape, and write the per-frame positions
    (OUT/positions.npz: x [frames+1, N, 3], time [frames+1]) and a preview.

    Given a scene CONFIG (.yaml/.yml/.json) instead, simulate its object in its scene and
    write per-frame Gaussians (OUT/gaussians.npz and OUT/frame_000.ply ..., the object's SH
    rotated into each frame; see `clflow render4d`) and the guidance camera's view."""
    if particles and particles.lower().endswith(CONFIG_SUFFIXES):
        from click.core import ParameterSource

        particle_only = [p.opts[0] for p in ctx.command.params
                         if p.name not in ("particles", "out_dir", "params_file", "preview", "max_output_gb",
                                           "overrides", "max_substeps", "object_only", "compressed")
                         and ctx.get_parameter_source(p.name) is ParameterSource.COMMANDLINE]
        if particle_only:
            raise click.UsageError(f"with a scene config, the config sets the simulation; drop "
                                   f"{', '.join(particle_only)}")
        simulate_scene(particles, params_file, out_dir, preview, max_output_gb, overrides, max_substeps, object_only,
                       compressed)
        return
    config_only = [name for name, given in (("--params", params_file), ("--set", overrides),
                                            ("--object-only", object_only), ("--compressed-ply", compressed))
                   if given]
    if config_only:
        raise click.UsageError(f"{', '.join(config_only)} needs a scene CONFIG (.yaml/.yml/.json)")
    out_dir = out_dir or "simulation"
    import logging
    from pathlib import Path

    import numpy as np
    import torch

    from clflow.errors import InputError
    from clflow.fileio import atomic_dir
    from clflow.limits import TRAJECTORY_REALS, check_memory, check_output
    from clflow.mpm import Grid, MaterialSpec, Simulator
    from clflow.mpm.preview import PREVIEW_SIZE, write_preview
    from clflow.mpm.shapes import lattice_fill, load_particles
    from clflow.mpm.substep import check_grid_memory
    from clflow.runtime import get_device
    from clflow.scene.config import DEFAULT_MAX_SUBSTEPS

    log = logging.getLogger("clflow.simulate")
    if resolution < 8 or not domain > 0:
        raise InputError(f"--grid must be >= 8 and --domain > 0, got {resolution}, {domain}")
    dx = domain / (resolution - 1)
    grid = Grid((resolution,) * 3, dx)
    dtype = torch.float64 if double else torch.float32
    device = ctx.obj.device() if ctx.obj else None
    check_grid_memory((device or get_device()).info, grid, dtype.itemsize)  # before filling the shape at dx / 2
    if particles:
        x, volume = load_particles(particles)
        if volume is None:
            volume = particle_volume if particle_volume is not None else (dx / 2) ** 3
            log.info("particle volume %.3g m^3 per particle (no 'volume' in %s)", volume, particles)
    else:
        spacing = dx / 2  # 2 particles per cell and axis
        c = _vec3(center, "--center") if center else [domain / 2] * 3
        x = lattice_fill(shape, size, c, spacing)
        volume = spacing**3
    sim = Simulator(
        x, volume, MaterialSpec(material, _params(params), density, model), grid,
        velocities=torch.tensor(_vec3(velocity, "--velocity"), dtype=torch.float64).expand(x.shape[0], 3),
        frame_dt=1.0 / fps, substeps=substeps, gravity=_vec3(gravity, "--gravity"),
        walls=None if walls == "none" else walls, wall_friction=wall_friction, dtype=dtype,
        device=device,
    )
    out = Path(out_dir)
    less = "simulate fewer --frames"
    image = 0 if preview == "none" else 3 * PREVIEW_SIZE**2  # bytes of an uncompressed preview frame
    check_output(out, (frames + 1) * (12 * sim.n + image), max_output_gb, f"{frames + 1:,} frames of {sim.n:,} particles", less)
    check_memory((frames + 1) * (sim.n * TRAJECTORY_REALS * dtype.itemsize + image),  # the preview is encoded at once
                 f"simulating {frames + 1:,} frames", less)
    click.echo(f"{sim.n:,} particles of {material}, {frames} frames x {sim.substeps} substeps (dt = {sim.dt:.3g} s, "
               f"limited by {sim.limit_reason(sim.state.v)})")
    limit = max_substeps or DEFAULT_MAX_SUBSTEPS
    if sim.substeps > limit:
        raise InputError(f"{sim.substeps} substeps per frame (dt = {sim.dt:.3g} s) is beyond the limit of {limit}; "
                         f"ways out: a softer material, a coarser --grid, fewer --substeps, or raise the limit "
                         f"with --max-substeps N")
    traj = sim.run(frames)
    target = out / ("preview.mp4" if preview == "mp4" else "preview")
    with atomic_dir(out) as tmp:  # all or nothing: a failure leaves OUT as it was
        np.savez(tmp / "positions.npz", x=traj.x.float().numpy(), time=traj.time.numpy())
        if preview != "none":
            write_preview(traj.x, grid.origin, grid.upper, tmp / target.name, fps, PREVIEW_SIZE)
    click.echo(f"wrote {out / 'positions.npz'}")
    if preview != "none":
        click.echo(f"wrote {target}")
