"""``clflow simulate``: run the MLS-MPM simulator on a particle file or a built-in shape."""

import click


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


@click.command("simulate")
@click.argument("particles", required=False, type=click.Path(dir_okay=False))
@click.option("--shape", type=click.Choice(["box", "sphere", "torus"]), default="box", show_default=True,
              help="Built-in shape when no particle file is given.")
@click.option("--size", default=0.3, show_default=True, help="Shape size (m): cube side, sphere or torus diameter.")
@click.option("--center", default=None, help="Shape centre 'x,y,z' (m); default: the middle of the domain.")
@click.option("--material", "-m", default="elastic", show_default=True, help="Material name (clflow.materials).")
@click.option("--param", "-p", "params", multiple=True, metavar="NAME=VALUE",
              help="Material parameter in SI units, e.g. -p youngs_modulus=2e5 (repeatable).")
@click.option("--model", default=None, help="Elastic model: fixed_corotated (default) or neo_hookean.")
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
@click.option("--out", "-o", "out_dir", default="simulation", show_default=True, type=click.Path(file_okay=False),
              help="Output folder: positions.npz and the preview.")
@click.option("--preview", type=click.Choice(["mp4", "png", "none"]), default="mp4", show_default=True,
              help="Preview video, PNG frames, or none.")
@click.pass_context
def simulate(ctx, particles, shape, size, center, material, params, model, density, velocity, domain, resolution,
             particle_volume, frames, fps, substeps, gravity, walls, wall_friction, double, out_dir, preview):
    """Simulate PARTICLES (.npz with 'positions' [N, 3] in m and optional 'volume' [N] in
    m^3, or a .ply point cloud) or a built-in shape, and write the per-frame positions
    (OUT/positions.npz: x [frames+1, N, 3], time [frames+1]) and a preview."""
    import logging
    from pathlib import Path

    import numpy as np
    import torch

    from clflow.errors import InputError
    from clflow.fileio import atomic_path
    from clflow.mpm import Grid, MaterialSpec, Simulator
    from clflow.mpm.preview import write_preview
    from clflow.mpm.shapes import lattice_fill, load_particles

    log = logging.getLogger("clflow.simulate")
    if resolution < 8 or not domain > 0:
        raise InputError(f"--grid must be >= 8 and --domain > 0, got {resolution}, {domain}")
    dx = domain / (resolution - 1)
    grid = Grid((resolution,) * 3, dx)
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
    dtype = torch.float64 if double else torch.float32
    sim = Simulator(
        x, volume, MaterialSpec(material, _params(params), density, model), grid,
        velocities=torch.tensor(_vec3(velocity, "--velocity"), dtype=torch.float64).expand(x.shape[0], 3),
        frame_dt=1.0 / fps, substeps=substeps, gravity=_vec3(gravity, "--gravity"),
        walls=None if walls == "none" else walls, wall_friction=wall_friction, dtype=dtype,
        device=ctx.obj.device() if ctx.obj else None,
    )
    click.echo(f"{sim.n:,} particles of {material}, {frames} frames x {sim.substeps} substeps (dt = {sim.dt:.3g} s)")
    traj = sim.run(frames)
    out = Path(out_dir)
    with atomic_path(out / "positions.npz") as tmp:
        np.savez(tmp, x=traj.x.float().numpy(), time=traj.time.numpy())
    click.echo(f"wrote {out / 'positions.npz'}")
    if preview != "none":
        target = out / ("preview.mp4" if preview == "mp4" else "preview")
        write_preview(traj.x, grid.origin, grid.upper, target, fps)
        click.echo(f"wrote {target}")
