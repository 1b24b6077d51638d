"""A `clflow eval sysid` case whose object is a trained 3DGS splat: the shape a real capture
gives the cell-sorted kernels (Gaussians clustered on the surface, not a procedural lattice).

The case is made as the benchmark makes it (its guidance at the optimiser's own resolution),
then its object's Gaussians in scene.ply are replaced by those of PLY (a `clflow reconstruct`
output, say), centred on the object and scaled uniformly to its largest side; the floor and the
guidance video stay the case's (a published guess may be unstable without the search: time
it from the truth). Time it with

    python experiments/trained_object_case.py OUT --ply trained.ply --case bird [--quick]
    clflow bench optimize --config OUT/config.yaml --at-truth --profile

A trained splat of the procedural sphere (60 views, 128 px; docs/gpu.md records what it showed):

    python -c "from clflow_datasets.multiview import make_multiview; make_multiview('cap', shape='sphere')"
    clflow reconstruct cap/images --transforms cap/transforms.json -o recon --iterations 3000
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path, help="folder for the case (config.yaml, scene.ply, guidance)")
    parser.add_argument("--ply", type=Path, required=True, help="the trained splat (a 3DGS PLY of one object)")
    parser.add_argument("--case", default="bird", help="a case of the paper's nine or the extra set (default bird)")
    parser.add_argument("--quick", action="store_true", help="the quick resolution of `clflow eval sysid --quick`")
    args = parser.parse_args(argv)

    import torch

    from clflow.scene.config import load_config
    from clflow.scene.load import select_objects
    from clflow.splat.gaussians import Gaussians
    from clflow.splat.ply import load_ply, save_ply
    from clflow_datasets.synthetic import make_case
    from clflow_datasets.sysid import FULL, QUICK
    from clflow_datasets.sysid_cases import CASES, EXTRA_CASES_FILE, load_cases

    catalogue = {**CASES, **load_cases(EXTRA_CASES_FILE)}
    if args.case not in catalogue:
        parser.error(f"{args.case!r} is no case; the cases: {', '.join(catalogue)}")
    config = make_case(args.out, catalogue[args.case], QUICK if args.quick else FULL)
    cfg = load_config(config)
    scene = load_ply(cfg.splats)
    labels = select_objects(cfg, scene.means.double())
    own, trained = scene.means[labels >= 0].double(), load_ply(args.ply)
    low, high = own.min(0).values, own.max(0).values
    t_low, t_high = trained.means.double().min(0).values, trained.means.double().max(0).values
    scale = float((high - low).max() / (t_high - t_low).max())
    means = (trained.means.double() - 0.5 * (t_low + t_high)) * scale + 0.5 * (low + high)
    degree = scene.sh_degree  # the case's floor: its SH degree (0) for both parts
    placed = Gaussians(
        means=means.to(scene.dtype),
        quats=trained.quats,
        log_scales=trained.log_scales + math.log(scale),
        opacity_logits=trained.opacity_logits,
        sh=trained.sh[:, : (degree + 1) ** 2].contiguous(),
    )
    save_ply(cfg.splats, Gaussians.cat([scene.select(labels < 0), placed]))
    moved = select_objects(cfg, torch.cat([scene.select(labels < 0).means, placed.means]).double())
    print(
        f"{config}: {args.case}'s {int((labels >= 0).sum()):,} Gaussians replaced by {len(placed):,} of {args.ply} "
        f"(scaled {scale:.3g}x; {int((moved >= 0).sum()):,} inside its selection)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
