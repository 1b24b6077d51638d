"""How far the observed flow is from the simulated one at the ground truth, and what that
does to the recovered parameters (docs/flow.md, "Observed-flow bias").

Per synthetic case (known parameters), DIS preset and flow.confidence: at the truth, the
least-squares slope of the observed on the simulated flow (1 = unbiased) and their EPE, both
weighted as the loss weighs pixels; the signed relative error (RE) of each parameter at the
minimum of the loss near the truth; the RE of the parameters `clflow optimize` recovers from
the case's guess.

    python experiments/flow_bias.py                                   # 96 px, every case and setting
    python experiments/flow_bias.py --size demo --preset medium --preset fine
    python experiments/flow_bias.py --case cube --preset medium --preset fine \\
        --confidence forward_backward --iterations 0

Results also as JSON (--json: the rows, the parameters and clflow.environment).
"""

from __future__ import annotations

import argparse
import os
import sys

# torch's OpenMP threads would spin and take the OpenCL CPU device's cores (docs/architecture.md)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

CASES = ("cube", "torus", "plasticine")


def synthetic_cases() -> dict:
    """The benchmark's cases: the demo's jelly cube, an elastic torus and a plasticine
    sphere, each pushed sideways on the floor (``SyntheticCase`` of datasets_tools)."""
    from clflow_datasets.demo import DEMO
    from clflow_datasets.synthetic import SyntheticCase, push_upper_part

    torus = SyntheticCase(
        shape="torus",
        material="elastic",
        truth={"youngs_modulus": 5e4, "poissons_ratio": 0.3},
        guess={"youngs_modulus": 5e3},
        forces=(push_upper_part(0.2),),
    )
    plasticine = SyntheticCase(
        shape="sphere",
        material="plasticine",
        truth={"youngs_modulus": 1e5, "poissons_ratio": 0.3, "yield_stress": 2e3},
        guess={"yield_stress": 2e2},
        optimize=("yield_stress",),
        forces=(push_upper_part(0.2, acceleration=20.0),),
    )
    return {"cube": DEMO, "torus": torus, "plasticine": plasticine}


SEARCH_HALF_WIDTH = 0.5  # z units (decades for moduli) either side of the truth


def loss_minimum(opt, z_truth: dict[str, float], name: str, steps: int = 16) -> float:
    """z of the minimum of the full-horizon loss along parameter ``name`` (the others at the
    truth), by golden-section search over z_truth +- SEARCH_HALF_WIDTH; the bracket shrinks
    to 0.618^steps of its width. A result at the bracket's edge means "there or beyond"."""
    ratio = (5**0.5 - 1) / 2

    def loss(z: float) -> float:
        return opt.objective.evaluate({**z_truth, name: z}, opt.problem.frames, with_grad=False).loss

    lo, hi = z_truth[name] - SEARCH_HALF_WIDTH, z_truth[name] + SEARCH_HALF_WIDTH
    a, b = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
    loss_a, loss_b = loss(a), loss(b)
    for _ in range(steps):
        if loss_a < loss_b:
            hi, b, loss_b = b, a, loss_a
            a = hi - ratio * (hi - lo)
            loss_a = loss(a)
        else:
            lo, a, loss_a = a, b, loss_b
            b = lo + ratio * (hi - lo)
            loss_b = loss(b)
    return (lo + hi) / 2


def measure_case(config, output, preset: str, confidence: str, iterations: int | None) -> dict:
    """Flow bias at the case's ground truth (slope of the observed on the simulated flow and
    EPE, px, both weighted as the loss weighs pixels: mask x confidence), the signed relative
    error of each parameter at the loss minimum near the truth (the bias the flow error puts
    into the parameters, whatever the optimiser does; ``beyond``: the names whose minimum is
    at the search's edge or further) and, unless ``iterations`` is 0, that of each parameter
    ``clflow optimize`` recovers from the case's guess."""
    import dataclasses

    import torch

    from clflow.benchmark import measure
    from clflow.flow.metrics import endpoint_error, flow_slope
    from clflow.pipeline.fit import Optimization
    from clflow.scene.config import load_config

    cfg = load_config(config)
    cfg = dataclasses.replace(
        cfg, output=output, flow=dataclasses.replace(cfg.flow, preset=preset, confidence=confidence)
    )
    if iterations is not None:
        cfg = dataclasses.replace(cfg, optimize=dataclasses.replace(cfg.optimize, iterations=max(iterations, 1)))
    opt = Optimization(cfg)
    truth = cfg.ground_truth
    z_truth = {n: float(p.encode(truth[n])) for n, p in opt.problem.params.items()}
    at_truth = opt.objective.evaluate(z_truth, opt.problem.frames, with_grad=False)
    simulated, observed, weight = (
        torch.stack(at_truth.flows).numpy(),
        opt.problem.views[0].observed.numpy(),
        opt.problem.views[0].weight.numpy(),
    )
    z_minimum = {n: loss_minimum(opt, z_truth, n) for n in z_truth}
    at_minimum = opt.problem.values(z_minimum)
    row = {
        "slope": flow_slope(observed, simulated, weight),
        "epe": endpoint_error(observed, simulated, weight),
        "kept": float(weight.sum() / opt.problem.views[0].mask.sum() / opt.problem.frames),
        "minimum": {n: (at_minimum[n] - truth[n]) / truth[n] for n in at_minimum},
        "beyond": {n for n, z in z_minimum.items() if abs(z - z_truth[n]) > 0.99 * SEARCH_HALF_WIDTH},
        "error": {},
        "seconds": 0.0,
    }
    if iterations != 0:
        timing = measure(opt.run, warmup=0)
        final = opt.problem.values(timing.result.z)
        row["seconds"], row["cpu_seconds"] = timing.median_wall, timing.median_cpu
        row["error"] = {n: (final[n] - truth[n]) / truth[n] for n in final}
    return row


def flow_bias(cases, presets, confidences, size: str, iterations: int | None) -> dict:
    """Measure and print each row (case, preset, confidence: slope, EPE px, share of the
    mask kept, RE at the loss minimum, RE recovered); returns the rows by "case preset confidence"."""
    import tempfile
    import warnings
    from pathlib import Path

    from clflow.environment import load_average
    from clflow.flow.optical_flow import CONFIDENCES, DIS_PRESETS
    from clflow.mpm.simulator import StabilityWarning
    from clflow_datasets.demo import QUICK
    from clflow_datasets.synthetic import Resolution, make_case

    warnings.simplefilter("ignore", StabilityWarning)
    resolution = QUICK if size == "quick" else Resolution()
    known = synthetic_cases()
    rows = {}
    print(
        f"load average {load_average()}; {resolution.image} px, {resolution.frames} frames, "
        f"{resolution.iterations if iterations is None else iterations} iterations"
    )
    print(
        f"{'case':11s} {'preset':10s} {'confidence':17s} {'slope':>6s} {'EPE px':>7s} {'kept':>5s}  "
        f"RE at the loss minimum; RE recovered"
    )
    with tempfile.TemporaryDirectory(prefix="clflow-flow-bias-") as folder:
        for name in cases or CASES:
            config = make_case(Path(folder) / name, known[name], resolution)
            for preset in presets or DIS_PRESETS:
                for confidence in confidences or CONFIDENCES:
                    row = measure_case(
                        config, Path(folder) / name / f"{preset}-{confidence}", preset, confidence, iterations
                    )
                    rows[f"{name} {preset} {confidence}"] = {**row, "beyond": sorted(row["beyond"])}
                    at_minimum = ", ".join(
                        f"{n} {'beyond ' if n in row['beyond'] else ''}{e:+.2%}" for n, e in row["minimum"].items()
                    )
                    recovered = ", ".join(f"{e:+.2%}" for e in row["error"].values())
                    timing = f" ({row['seconds']:.0f} s)" if row["error"] else ""
                    print(
                        f"{name:11s} {preset:10s} {confidence:17s} {row['slope']:6.3f} {row['epe']:7.3f} "
                        f"{row['kept']:5.2f}  {at_minimum}; {recovered or '-'}{timing}"
                    )
    print(f"load average {load_average()}")
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    repeatable = (  # (option, dest, metavar, what), each repeatable, default: all
        ("--case", "cases", "{" + ",".join(CASES) + "}", "only these cases"),
        ("--preset", "presets", "PRESET", "DIS presets to compare"),
        ("--confidence", "confidences", "SETTING", "flow.confidence settings to compare"),
    )
    for option, dest, metavar, what in repeatable:
        parser.add_argument(
            option, dest=dest, metavar=metavar, action="append", default=[], help=f"{what} (repeatable; default all)"
        )
    parser.add_argument(
        "--size",
        choices=("quick", "demo"),
        default="quick",
        help="quick: 96 px, 8 frames, 14 iterations (the QUICK demo); demo: 160 px, 12 frames, 20",
    )
    parser.add_argument(
        "--iterations",
        type=_count,
        metavar="N",
        default=None,
        help="optimisation iterations (0: the flow bias only); default: the size's",
    )
    parser.add_argument("--json", metavar="PATH", help="also write the rows, the parameters and the environment")
    args = parser.parse_args(argv)
    if unknown := sorted(set(args.cases) - set(CASES)):
        parser.error(f"--case {', '.join(unknown)}: not among {', '.join(CASES)}")
    parameters = {k: v for k, v in vars(args).items() if k != "json"}
    rows = flow_bias(**parameters)
    if args.json:
        from clflow.benchmark import write_record

        write_record(args.json, "flow-bias", parameters, rows)
        print(f"wrote {args.json}")
    return 0


def _count(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{value} is below 0")
    return value


if __name__ == "__main__":
    sys.exit(main())
