"""The bundled demos: a jelly cube on a checkered floor, its upper part pushed sideways;
and a pair of cubes of two stiffnesses dropped side by side (a scene of two objects).

The jelly: a :class:`~clflow_datasets.synthetic.SyntheticCase`, a 0.2 m cube, elastic with
E = 20 kPa and nu = 0.3, 1000 kg/m^3, pushed at 12 m/s^2 for 0.12 s above a sticky ground;
the config starts from E = 2 kPa (10x low). ``make_demo(folder)`` writes it (scene.ply,
config_truth.yaml, guidance/ and guidance.mp4, config.yaml, case.json).

The pair: a :class:`~clflow_datasets.scene_cases.SceneCase`, a soft jelly (E = 20 kPa) and
a stiffer block (E = 100 kPa), 0.2 m cubes 0.1 m apart, falling at 1 m/s onto a sticky
ground from 0.02 m; each E starts 10x low and is identified from the one video
(``jelly.youngs_modulus``, ``block.youngs_modulus``). ``make_pair_demo(folder)`` writes it.

Each optimisation starts with a 4-frame horizon: that loss falls monotonically towards the
truth from far below, where the full horizon's has a local maximum (docs/pipeline.md).
"""

from __future__ import annotations

from pathlib import Path

from clflow_datasets.scene_cases import CaseObject, SceneCase
from clflow_datasets.synthetic import Resolution, SyntheticCase, make_case, push_upper_part

TRUTH = {"youngs_modulus": 2.0e4, "poissons_ratio": 0.3}  # a soft jelly, Pa

DEMO = SyntheticCase(
    shape="cube",
    size=0.2,
    material="elastic",
    truth=TRUTH,
    guess={"youngs_modulus": TRUTH["youngs_modulus"] / 10.0},
    density=1000.0,
    optimize=("youngs_modulus",),
    learning_rate=0.2,
    horizon=(4, 1),
    forces=(push_upper_part(0.2),),
    ground="sticky",
    spread=1.0,
)


def _falling_cube(name: str, x: float, youngs_modulus: float) -> CaseObject:
    """A 0.2 m elastic cube centred at (x, 0.12, 0) m (0.02 m above the ground) falling at
    1 m/s, its E guessed 10x low."""
    return CaseObject(
        name,
        "cube",
        0.2,
        (x, 0.12, 0.0),
        "elastic",
        truth={"youngs_modulus": youngs_modulus, "poissons_ratio": 0.3},
        guess={"youngs_modulus": youngs_modulus / 10.0},
        optimize=("youngs_modulus",),
        velocity=(0.0, -1.0, 0.0),
    )


PAIR = SceneCase(
    objects=(_falling_cube("jelly", -0.15, 2.0e4), _falling_cube("block", 0.15, 1.0e5)),
    spread=0.3,
    horizon=(4, 1),
)

QUICK = Resolution(object_detail=8, floor_side=24, image=96, grid=16, frames=8, iterations=14)


def benchmark_size(gaussians: int, image: int = 256, grid: int = 24, frames: int = 12) -> Resolution:
    """A resolution of the demo with about ``gaussians`` Gaussians, a fifth on the object."""
    detail = max(2, round((gaussians / 5 / 6) ** 0.5))
    floor_side = max(2, round(max(0, gaussians - 6 * detail**2) ** 0.5))
    return Resolution(object_detail=detail, floor_side=floor_side, image=image, grid=grid, frames=frames)


def make_demo(folder: str | Path, resolution: Resolution = Resolution(), seed: int = 0) -> Path:
    """Write the demo case into ``folder``; returns the path of its ``config.yaml``."""
    return make_case(folder, DEMO, resolution, seed)


def make_pair_demo(folder: str | Path, resolution: Resolution = Resolution(), seed: int = 0) -> Path:
    """Write the two-object demo case into ``folder``; returns the path of its ``config.yaml``."""
    return make_case(Path(folder), PAIR, resolution, seed, truth_scale=2)


__all__ = ["DEMO", "PAIR", "QUICK", "TRUTH", "benchmark_size", "make_demo", "make_pair_demo"]
