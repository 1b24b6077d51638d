"""The checkpoint of an optimisation: its state after every iteration, on disk."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

from clflow.errors import InputError
from clflow.fileio import atomic_write_text
from clflow.fileio.reading import parse_json
from clflow.pipeline.fit.problem import Problem
from clflow.pipeline.fit.state import OptimizerState, check_same_config, config_digests


class Checkpoint:
    """The file an optimiser's state is saved in after every iteration (``path``; a search
    start's polish has its own) and read from on --resume, tied to the config by its
    digests (:func:`config_digests`)."""

    def __init__(self, path: Path, problem: Problem):
        self.path, self.problem = path, problem

    def exists(self) -> bool:
        return self.path.exists()

    def load(self) -> OptimizerState:
        """The saved state; InputError when it cannot be read, optimises other variables or
        was saved under another config."""
        try:
            data = parse_json(self.path.read_text())
            state = OptimizerState(**data["state"])
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise InputError(f"cannot resume from {self.path}: {exc}") from None
        if set(state.z) != set(self.problem.variables):
            raise InputError(f"{self.path} optimises {sorted(state.z)}, the config {sorted(self.problem.variables)}")
        check_same_config(self.path, data.get("config_digests"), self.problem.cfg)
        return state

    def save(self, state: OptimizerState, **extra) -> None:
        """``state`` into the file, with ``extra`` entries."""
        atomic_write_text(
            self.path,
            json.dumps(
                {
                    "config": str(self.problem.cfg.source),
                    "state": asdict(state),
                    "config_digests": config_digests(self.problem.cfg),
                    **extra,
                }
            ),
        )
