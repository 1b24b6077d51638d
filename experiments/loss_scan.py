"""Scan an identification's loss along one parameter, with the gradients the optimiser sees.

For a finished `clflow eval sysid` case (or any `clflow optimize` folder's config): from its
final point, each value of PARAM on the scan is run on the model's grid at the final point's
substeps (or on --grid's, at its own stable substeps) and gives
  - loss: against the targets calibrated at the final point (what Levenberg-Marquardt
    compares its trial steps with), or at --calibrate-at,
  - self-consistent loss: against the estimator's error measured at the value itself, over
    the camera shifts that score a result (Objective.final_shifts: what the benchmark's
    "loss found / at truth" use), with flow.bias_correction,
  - dloss/dz by the adjoint, and the backward difference of LM_STEP that the optimiser's
    Jacobian takes, and the central difference across the scan's neighbours.

    python experiments/loss_scan.py OUT/cases/trophy/config.yaml friction_angle 36 41 --points 21 --json scan.json
    python experiments/loss_scan.py OUT/cases/sand_heap/config.yaml friction_angle 48.5 51.5 --points 3 --grid 84

Results also as JSON (--json). docs/pipeline.md records what the scans showed.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", type=Path, help="the case's config.yaml (its optimisation finished)")
    parser.add_argument("param", help="the parameter to scan, e.g. friction_angle")
    parser.add_argument("low", type=float, help="first value (SI units; degrees for an angle)")
    parser.add_argument("high", type=float, help="last value")
    parser.add_argument("--points", type=int, default=11, help="values on the scan, evenly spaced (default 11)")
    parser.add_argument("--no-self-consistent", action="store_true", help="skip the self-consistent loss")
    parser.add_argument(
        "--calibrate-at",
        type=float,
        metavar="VALUE",
        help="measure the flow estimator's error at this value of PARAM first (default: keep the final point's)",
    )
    parser.add_argument(
        "--grid",
        type=int,
        metavar="NODES",
        help="run the scan on a grid of NODES nodes over the same domain (default: the model's): "
        "how far the discretisation moves the minimum",
    )
    parser.add_argument("--json", type=Path, help="write the scan here")
    args = parser.parse_args(argv)

    import numpy as np

    from clflow.pipeline.fit import Optimization
    from clflow.pipeline.fit.objective import LM_STEP
    from clflow.scene.config import load_config

    opt = Optimization(load_config(args.config))
    state = opt.run(resume=True)
    if args.param not in opt.problem.params:
        raise SystemExit(f"{args.param} is not optimised here; the parameters are {', '.join(opt.problem.params)}")
    encode = opt.problem.params[args.param].encode
    frames = opt.problem.frames
    print(
        f"final point {opt.problem.values(state.z)} at {state.substeps} substeps per frame, loss {state.best['loss']:.5g}"
    )
    grid = opt.problem.model_grid if args.grid is None else args.grid
    substeps = state.substeps if grid == opt.problem.model_grid else 1  # another grid: its own stable substeps
    if args.calibrate_at is not None and opt.problem.corrects_bias:
        # the run's own calibration file stays as the run left it: this one goes elsewhere
        opt.objective.calibration_file = Path(tempfile.mkdtemp(prefix="loss-scan-")) / "estimator_error.npz"
        z = {**state.z, args.param: float(encode(args.calibrate_at))}
        at = dataclasses.replace(state, z=z, calibrated_at=None)
        opt.objective.calibrate(
            at, opt.objective.evaluate(z, frames, with_grad=False, min_substeps=substeps, grid=grid), frames
        )
        print(f"targets calibrated at {args.param} = {args.calibrate_at:g}")
    rows = []
    for value in np.linspace(args.low, args.high, args.points):
        started = time.perf_counter()
        z = {**state.z, args.param: float(encode(float(value)))}
        at = opt.objective.evaluate(z, frames, min_substeps=substeps, variables=(args.param,), grid=grid)
        nearby = opt.objective.evaluate(
            {**z, args.param: z[args.param] - LM_STEP}, frames, with_grad=False, min_substeps=at.substeps, grid=grid
        )
        row = {
            "value": float(value),
            "z": z[args.param],
            "loss": at.loss,
            "grid": grid,
            "substeps": at.substeps,
            "adjoint_dz": at.grads[args.param],
            "lm_backward_difference_dz": (at.loss - nearby.loss) / LM_STEP,
        }
        if not args.no_self_consistent:
            row["self_consistent_loss"] = opt.objective.self_consistent_loss(at, frames, opt.objective.final_shifts)
        row["seconds"] = time.perf_counter() - started
        rows.append(row)
        print(
            f"{value:9.4g}  loss {row['loss']:.5g}"
            + (f"  self-consistent {row['self_consistent_loss']:.5g}" if "self_consistent_loss" in row else "")
            + f"  dL/dz adjoint {row['adjoint_dz']:+.4g}  LM difference {row['lm_backward_difference_dz']:+.4g}"
            f"  ({grid} nodes, {row['substeps']} substeps, {row['seconds']:.0f} s)",
            flush=True,
        )
    for before, row, after in zip(rows, rows[1:], rows[2:]):
        row["scan_central_difference_dz"] = (after["loss"] - before["loss"]) / (after["z"] - before["z"])
    record = {"config": str(args.config), "param": args.param, "final": opt.problem.values(state.z), "rows": rows}
    record["calibrated_at"] = args.calibrate_at
    if args.json:
        tmp = args.json.with_name(f".{args.json.name}.tmp")
        tmp.write_text(json.dumps(record, indent=2) + "\n")
        tmp.replace(args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
