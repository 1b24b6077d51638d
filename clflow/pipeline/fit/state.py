"""The state of an optimisation: what it holds between iterations and its checkpoint; what one
evaluation of the loss returns; the digests that tie a checkpoint to its config."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from clflow.errors import ClflowError, InputError
from clflow.fileio.reading import parse_json
from clflow.scene.config import SceneConfig, config_record

if TYPE_CHECKING:
    from clflow.mpm.autograd import Frames

log = logging.getLogger(__name__)

LM_DAMPING = 1e-2  # initial damping (relative to the diagonal of J^T J)


@dataclass
class OptimizerState:
    """Everything needed to continue an optimisation exactly (saved as JSON, exact floats)."""

    iteration: int
    z: dict[str, float]
    m: dict[str, float]
    v: dict[str, float]
    step_scale: float = 1.0
    history: list[dict] = field(default_factory=list)
    momentum_steps: int = 0  # gradients in m since its last restart (for Adam's bias correction)
    # substeps per frame at least (automatic substeps) of the next run: Adam's never fewer than
    # an earlier iteration needed, so the loss stays one smooth function of the parameters
    # instead of jumping where a NaN/CFL retry would change dt; Levenberg-Marquardt's those
    # of its best point, from which each step is taken
    substeps: int = 1
    # the global phase's samples so far ({"z", "params", "loss", "seconds"}; loss None where
    # the simulation failed) and whether it is over (its best point is then z)
    search: list[dict] = field(default_factory=list)
    searched: bool = False
    # Levenberg-Marquardt: damping, and the best point so far (its z, loss and horizon)
    damping: float = LM_DAMPING
    best: dict | None = None
    # every iteration that failed or was unstable and was rolled back: {"iteration", "phase",
    # "reason", "params" (the rejected point), "back_to" (the last good parameters)}
    rollbacks: list[dict] = field(default_factory=list)
    # flow.bias_correction: the point whose simulation measured the flow estimator's error
    # (its z, frames and grid nodes; the error itself is saved beside the checkpoint), None before any
    calibrated_at: dict | None = None
    converged: bool = False  # Levenberg-Marquardt: no step from the best point promises progress
    # optimize.search.starts: the best search samples' z, each polished by a few Levenberg-Marquardt
    # iterations in turn, and per polished start its best point {"z", "loss", "params"}, the
    # substeps its polish ended with ("substeps": the best point's, or 1 after a step from it)
    # and, with a coarser search grid, its "model_loss" on the main phase's grid
    starts: list[dict] = field(default_factory=list)
    polished: list[dict] = field(default_factory=list)
    # flow.bias_correction with Levenberg-Marquardt: what the line search of the own-calibration
    # loss did after LM stopped (Steps.own_loss_line_search), None before it ran
    line_search: dict | None = None


class UnstableRun(ClflowError):
    """A simulation finished but is not to be trusted (CFL broken, particles clamped at the
    grid's edge): the optimiser rejects it like a NaN."""


@dataclass
class Evaluation:
    """The loss at one point: value, dloss/dz per parameter, simulated flows [H, W, 2] per
    frame step, the simulation (x [T+1, M, 3], F [T+1, M, 3, 3], substeps per frame) and the
    grid it ran on (nodes along the domain's longest side)."""

    loss: float
    grads: dict[str, float]
    flows: list[torch.Tensor]
    trajectory: Frames
    grid: int
    more_flows: tuple[list[torch.Tensor], ...] = ()  # the flows seen by views 1.. (several guidance views)

    @property
    def substeps(self) -> int:
        return self.trajectory.substeps


def _by_content(value):
    """``value`` (a config field as asdict gives it) with every path replaced by the digest
    of what it holds (clflow.fileio.content_digest)."""
    from clflow.fileio import content_digest

    if isinstance(value, Path):
        return content_digest(value)
    if isinstance(value, dict):
        return {k: _by_content(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_by_content(v) for v in value]
    return value


def config_digests(cfg: SceneConfig, by_path: bool = False) -> dict[str, str]:
    """A SHA-256 of each top-level field of the resolved config (canonical JSON; files and
    folders by their contents, so a moved run resumes; ``by_path``: by their paths, as
    checkpoints before that were saved), except ``output``, ``optimize.iterations``
    (``--resume --iterations N`` extends a run), ``simulation.max_substeps`` and, under a
    budget, ``simulation.grid_resolution`` (the budget's to choose): what a resumed run must
    share with its checkpoint."""
    import hashlib

    fields = config_record(cfg)
    fields.pop("output", None)
    fields["optimize"].pop("iterations", None)
    fields["simulation"].pop("max_substeps", None)  # a run stopped by the limit may resume with a higher one
    if fields["optimize"].get("prior") == "none":  # no prior: the digests of checkpoints from before it
        fields["optimize"].pop("prior")
    if fields["optimize"].get("budget") is not None:  # the main grid is the budget's choice (budget.json)
        fields["simulation"].pop("grid_resolution", None)
    if not fields["more_views"]:  # one view: the digests of checkpoints from before several views
        fields.pop("more_views")
    if fields.get("generate") is None:  # no generated video: the digests of checkpoints from before it
        fields.pop("generate", None)
    if not by_path:
        fields = _by_content(fields)
    return {
        name: hashlib.sha256(json.dumps(value, sort_keys=True, default=str).encode()).hexdigest()[:16]
        for name, value in fields.items()
    }


def check_same_config(checkpoint: Path, saved, cfg: SceneConfig) -> None:
    """InputError when the config digests ``saved`` in ``checkpoint`` (None: an older
    checkpoint, which has none) are not those of ``cfg``: a resumed run goes on with the config
    it was started with."""
    if not isinstance(saved, dict):
        return
    digests = config_digests(cfg)
    if saved != digests and saved != config_digests(cfg, by_path=True):
        changed = sorted(k for k in saved.keys() | digests.keys() if saved.get(k) != digests.get(k))
        raise InputError(
            f"cannot resume from {checkpoint}: the config changed since it was saved "
            f"({', '.join(changed)}); give another -o/--out, or delete the checkpoint to start over"
        )


def check_resume(checkpoint: Path, cfg: SceneConfig) -> None:
    """:func:`check_same_config` of a checkpoint file, before any work; one that is not JSON
    (or nests too deep) is refused as the optimiser would refuse it when it loads it, one
    that cannot be read or holds other things is the optimiser's to refuse."""
    try:
        data = parse_json(checkpoint.read_text())
    except OSError:
        return
    except ValueError as exc:
        raise InputError(f"cannot resume from {checkpoint}: {exc}") from None
    if isinstance(data, dict):
        check_same_config(checkpoint, data.get("config_digests"), cfg)
