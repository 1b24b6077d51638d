"""``clflow simulate``: run the MLS-MPM simulator on a particle file or a built-in shape."""

import click

from clflow_cli.options import (
    InputFile,
    Numbers,
    aliased_option,
    count_option,
    given_options,
    max_output_option,
    max_substeps_option,
    out_option,
    set_option,
)


def _params(ctx, param, items):
    """``--param NAME=VALUE`` items as {name: value (SI)}."""
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
#: what only a built-in shape takes (a particle file brings its own), and only a particle file
SHAPE_OPTIONS = ("shape", "size", "center")
FILE_OPTIONS = ("particle_volume",)
# what a scene CONFIG run takes; every other option describes particles and is refused with one
SCENE_OPTIONS = (
    "particles",
    "out_dir",
    "params_file",
    "preview",
    "max_output_gb",
    "overrides",
    "max_substeps",
    "object_only",
    "compressed",
)


@click.command("simulate")
@click.argument("particles", required=False, type=InputFile())
@click.option("--shape", type=click.Choice(["box", "sphere", "torus"]), default="box", show_default=True,
              help="Built-in shape when no particle file is given.")  # fmt: skip
@click.option("--size", type=click.FloatRange(0, min_open=True), default=0.3, show_default=True,
              help="Shape size (m): cube side, sphere or torus diameter.")  # fmt: skip
@click.option("--center", type=Numbers(3, "X,Y,Z"), default=None,
              help="Shape centre (m); default: the middle of the domain.")  # fmt: skip
@click.option("--material", "-m", default="elastic", show_default=True, help="Material name (clflow.materials).")
@click.option("--param", "-p", "params", multiple=True, metavar="NAME=VALUE", callback=_params,
              help="One material parameter in SI units, e.g. -p youngs_modulus=2e5 (repeatable).")  # fmt: skip
@click.option("--model", default=None, help="Elastic model: fixed_corotated (default) or neo_hookean; sand: drucker_prager "
                                           "(default) or volume_corrected.")  # fmt: skip
@click.option("--density", type=click.FloatRange(0, min_open=True), default=None,
              help="Density (kg/m^3); default: the material's.")  # fmt: skip
@click.option("--velocity", type=Numbers(3, "VX,VY,VZ"), default="0,0,0", show_default=True,
              help="Initial velocity (m/s).")  # fmt: skip
@click.option("--domain", type=click.FloatRange(0, min_open=True), default=1.0, show_default=True,
              help="Side of the cubic domain (m), origin at 0.")  # fmt: skip
@click.option("--grid", "resolution", type=click.IntRange(min=8), default=64, show_default=True,
              help="Grid nodes per axis.")  # fmt: skip
@click.option("--particle-volume", type=click.FloatRange(0, min_open=True), default=None,
              help="Rest volume per particle (m^3) for particle files without one; default (dx/2)^3.")  # fmt: skip
@count_option("--frames", default=24, help="Frames to simulate.")
@click.option("--fps", type=click.FloatRange(0, min_open=True), default=24.0, show_default=True,
              help="Frames per second.")  # fmt: skip
@click.option("--substeps", type=click.IntRange(min=1), default=None,
              help="Substeps per frame (default: the stable count).")  # fmt: skip
@click.option("--gravity", type=Numbers(3, "GX,GY,GZ"), default="0,-9.81,0", show_default=True,
              help="Gravity (m/s^2).")  # fmt: skip
@click.option("--walls", type=click.Choice(["separate", "slip", "sticky", "none"]), default="separate",
              show_default=True, help="Domain-wall condition.")  # fmt: skip
@click.option("--wall-friction", type=click.FloatRange(min=0), default=0.0, show_default=True,
              help="Coulomb friction of the walls.")  # fmt: skip
@click.option("--double", is_flag=True, help="Simulate in float64.")
@out_option("out_dir", "Output folder [default: simulation; for a config: its output/simulation].")
@aliased_option("--params-from", "params_file", aliases=("--params",), type=InputFile(),
                metavar="PARAMS.JSON",
                help="With a CONFIG: simulate with the material, density and velocity of this params.json "
                     "(clflow optimize's result).")  # fmt: skip
@click.option("--preview", type=click.Choice(["mp4", "png", "none"]), default="mp4", show_default=True,
              help="Preview video, PNG frames, or none.")  # fmt: skip
@max_output_option
@set_option("With a CONFIG: set a config key, the value read as YAML, e.g. --set simulation.frames=48 "
            "(repeatable; checked like the file).")  # fmt: skip
@max_substeps_option("Refuse a run needing more substeps per frame [default: a config's simulation.max_substeps, "
                     "else 2000].")  # fmt: skip
@click.option("--object-only", is_flag=True,
              help="With a CONFIG: PLY frames of the object alone, the static Gaussians once in OUT/static.ply.")  # fmt: skip
@click.option("--compressed-ply", "compressed", is_flag=True,
              help="With a CONFIG: write the PLYs compressed (frame_000.compressed.ply ..., the format SuperSplat and "
                   "PlayCanvas read), about a quarter of the size.")  # fmt: skip
@click.pass_context
def simulate(
    ctx,
    particles,
    out_dir,
    params_file,
    preview,
    max_output_gb,
    overrides,
    max_substeps,
    object_only,
    compressed,
    **particle_run,
):
    """Simulate PARTICLES (.npz with 'positions' [N, 3] in m and optional 'volume' [N] in
    m^3, or a .ply point cloud) or a built-in shape, and write the per-frame positions
    (OUT/positions.npz: x [frames+1, N, 3], time [frames+1]) and a preview.

    Given a scene CONFIG (.yaml/.yml/.json) instead, simulate its object in its scene and
    write per-frame Gaussians (OUT/gaussians.npz and OUT/frame_000.ply ..., the object's SH
    rotated into each frame; see `clflow render4d`) and the guidance camera's view."""
    if particles and particles.lower().endswith(CONFIG_SUFFIXES):
        from clflow.pipeline.runs import simulate_scene
        from clflow_cli.progress import progress

        particle_only = given_options(ctx, lambda name: name not in SCENE_OPTIONS)
        if particle_only:
            raise click.UsageError(
                f"with a scene config, the config sets the simulation; drop {', '.join(particle_only)}"
            )
        simulate_scene(
            particles,
            params_file,
            out_dir,
            preview,
            max_output_gb,
            overrides,
            max_substeps,
            echo=click.echo,
            object_only=object_only,
            compressed=compressed,
            progress=progress,
        )
        return
    config_only = [
        name
        for name, given in (
            ("--params-from", params_file),
            ("--set", overrides),
            ("--object-only", object_only),
            ("--compressed-ply", compressed),
        )
        if given
    ]
    if config_only:
        raise click.UsageError(f"{', '.join(config_only)} needs a scene CONFIG (.yaml/.yml/.json)")
    from clflow.errors import InputError
    from clflow.mpm.shapes import PARTICLE_SUFFIXES

    if particles and not particles.lower().endswith(PARTICLE_SUFFIXES):
        kinds = ", ".join(PARTICLE_SUFFIXES + CONFIG_SUFFIXES)
        raise InputError(f"{particles}: not a particle file or a scene config (the file name must end in {kinds})")
    unused = given_options(ctx, lambda name: name in (SHAPE_OPTIONS if particles else FILE_OPTIONS))
    if unused and particles:
        raise click.UsageError(f"{particles} has its own particles, not a built-in shape: drop {', '.join(unused)}")
    if unused:
        raise click.UsageError(f"{', '.join(unused)} applies to a PARTICLES file, not to a built-in shape: drop it")
    from clflow.pipeline.runs import ParticleRun, simulate_particles
    from clflow_cli.progress import progress

    simulate_particles(
        ParticleRun(particles, **particle_run),
        out_dir or "simulation",
        preview,
        max_output_gb,
        max_substeps,
        device=ctx.obj.device() if ctx.obj else None,
        echo=click.echo,
        progress=progress,
    )
