"""Where a benchmark case's loss is lowest along one parameter when the case or the model changes.

Makes case NAME (one of `clflow eval sysid`'s nine or of its extra set) in OUT unless made
there, with its truth and optimiser at PIC/FLIP blend --flip, the truth's values changed by
--truth and its grid and image refined by --truth-scale, then scores PARAM at each of
--values with the other optimised parameters at the truth's: the loss against the flow
estimator's error measured at that point, over the camera shifts that score a result (what
`eval sysid` reports as "loss found / at truth"). No optimisation runs, so a change of the
model (--grid, --substep-dt, --fill-spacing apply to the optimiser's model only) shows in a
few minutes how far it moves the minimum. Prints a JSON line per value and the minimum of
the parabola through the three lowest.

    python experiments/case_variant_losses.py sand_ring friction_angle --values 23.5 25 26.5 --out /tmp/ring
    python experiments/case_variant_losses.py sand_heap friction_angle --values 48.5 50 51.5 \\
        --truth youngs_modulus=1e5 --out /tmp/heap_soft

docs/pipeline.md ("What moves the sand's grid bias") records what it showed.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Callable

MADE = "variant.json"  # what the case in a folder was made with


def make_variant(name: str, out: Path, resolution, truth: dict[str, float], truth_scale: int, seed: int = 0):
    """Case ``name`` with ``truth`` values replaced, made in ``out`` at ``resolution`` (a
    clflow_datasets Resolution) unless made there with the same; returns the case."""
    from clflow_datasets import sysid_cases
    from clflow_datasets.synthetic import make_case

    cases = {**sysid_cases.load_cases(sysid_cases.EXTRA_CASES_FILE), **sysid_cases.CASES}
    if name not in cases:
        raise SystemExit(f"no case {name!r}; the cases: {', '.join(sorted(cases))}")
    case = cases[name]
    unknown = sorted(set(truth) - set(case.truth))
    if unknown:
        raise SystemExit(f"--truth {', '.join(unknown)}: not among {name}'s truth values ({', '.join(case.truth)})")
    case = dataclasses.replace(case, truth={**case.truth, **truth})
    made = {"case": name, "truth": case.truth, "truth_scale": truth_scale, "resolution": dataclasses.asdict(resolution)}
    record = out / MADE
    if record.exists():
        if json.loads(record.read_text()) != json.loads(json.dumps(made)):
            raise SystemExit(f"{out} holds a case made otherwise ({record}); give another --out")
        return case
    if out.exists() and any(out.iterdir()):
        raise SystemExit(f"{out} is not empty and holds no {MADE}; give a new or empty --out")
    make_case(out, case, resolution, seed, truth_scale=truth_scale)
    record.write_text(json.dumps(made, indent=2) + "\n")  # last: an interrupted making leaves none
    return case


def losses_along(
    config: Path,
    truth: dict[str, float],
    param: str,
    values: list[float],
    *,
    grid: int | None = None,
    substep_dt: float | None = None,
    fill_spacing: float | None = None,
    report: Callable[[dict], None] = lambda row: None,
) -> list[dict]:
    """The own-calibration loss of the case at ``config`` at each of ``values`` of ``param``
    (SI), the other optimised parameters at ``truth``; rows of value, loss, grid, substeps."""
    from clflow.pipeline.fit import Optimization
    from clflow.scene.config import load_config

    cfg = load_config(config)
    sim = cfg.simulation
    cfg = dataclasses.replace(
        cfg, simulation=dataclasses.replace(sim, grid_resolution=grid or sim.grid_resolution, substep_dt=substep_dt)
    )
    if fill_spacing is not None:
        fill = lambda o: dataclasses.replace(o.fill, spacing=fill_spacing)  # noqa: E731
        cfg = dataclasses.replace(cfg, objects=tuple(dataclasses.replace(o, fill=fill(o)) for o in cfg.objects))
    opt = Optimization(cfg)
    if param not in opt.problem.params:
        raise SystemExit(f"{param} is not optimised in {config}; its parameters: {', '.join(opt.problem.params)}")
    z = {name: float(p.encode(truth[name])) for name, p in opt.problem.params.items()}
    rows = []
    for value in values:
        started = time.perf_counter()
        z[param] = float(opt.problem.params[param].encode(value))
        at = opt.objective.evaluate(z, opt.problem.frames, with_grad=False)
        loss = opt.objective.self_consistent_loss(at, opt.problem.frames, opt.objective.final_shifts)
        rows.append({"value": value, "loss": loss, "grid": opt.problem.model_grid, "substeps": at.substeps})
        report(rows[-1] | {"s": round(time.perf_counter() - started)})
    return rows


def parabola_minimum(rows: list[dict]) -> float | None:
    """The minimum of the parabola through the three lowest losses (None: fewer, or no minimum)."""
    import numpy as np

    if len(rows) < 3:
        return None
    low = sorted(np.argsort([r["loss"] for r in rows])[:3])
    a, b, _ = np.polyfit([rows[i]["value"] for i in low], [rows[i]["loss"] for i in low], 2)
    return float(-b / (2 * a)) if a > 0 else None


def _assignment(text: str) -> tuple[str, float]:
    key, sep, value = text.partition("=")
    try:
        if key and sep:
            return key, float(value)
    except ValueError:
        pass
    raise argparse.ArgumentTypeError(f"{text!r}: expected NAME=VALUE, e.g. youngs_modulus=1e5")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("case", help="a case of the nine or of the extra set, e.g. sand_ring")
    parser.add_argument("param", help="the parameter to score, e.g. friction_angle")
    parser.add_argument("--values", type=float, nargs="+", required=True, help="values of PARAM (SI; degrees)")
    parser.add_argument("--out", type=Path, required=True, help="the case's folder (made here unless made)")
    parser.add_argument("--quick", action="store_true", help="the benchmark's --quick resolution")
    parser.add_argument("--flip", type=float, help="PIC/FLIP blend of truth and model (default: the benchmark's)")
    parser.add_argument("--truth", type=_assignment, action="append", default=[], metavar="NAME=VALUE")
    parser.add_argument(
        "--truth-scale", type=int, default=2, help="the truth's refinement (default 2, the benchmark's)"
    )
    parser.add_argument("--grid", type=int, metavar="NODES", help="the model's grid (default: the case's)")
    parser.add_argument("--substep-dt", type=float, metavar="S", help="the model's substep (default: stable)")
    parser.add_argument("--fill-spacing", type=float, metavar="M", help="the model's particle spacing")
    args = parser.parse_args(argv)

    from clflow_datasets import sysid

    resolution = sysid.QUICK if args.quick else sysid.FULL
    if args.flip is not None:
        resolution = dataclasses.replace(resolution, flip=args.flip)
    started = time.perf_counter()
    case = make_variant(args.case, args.out, resolution, dict(args.truth), args.truth_scale)
    print(json.dumps({"case": args.case, "made_s": round(time.perf_counter() - started)}), flush=True)
    rows = losses_along(
        args.out / "config.yaml",
        case.truth,
        args.param,
        args.values,
        grid=args.grid,
        substep_dt=args.substep_dt,
        fill_spacing=args.fill_spacing,
        report=lambda row: print(json.dumps(row), flush=True),
    )
    print(json.dumps({"parabola_minimum": parabola_minimum(rows)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
