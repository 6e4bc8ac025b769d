"""Cumulative training history carried by checkpoints and exported weights.

Weights trained in several runs (resumed, or started from earlier weights with --init-weights)
keep one record per run, so that the total training a set of weights has had is known.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any


@dataclass
class RunRecord:
    """One training run.

    origin: "scratch", "resume" or "init-weights"; device: what trained it (e.g. "cpu",
    "NVIDIA H100 80GB HBM3"); processes: DDP world size; first_step/last_step: optimiser steps
    of the run's step counter; pairs: training pairs seen (all processes); minutes: wall time.
    """

    started: str
    origin: str
    model: str
    device: str
    processes: int
    first_step: int
    last_step: int
    pairs: int = 0
    minutes: float = 0.0
    final_loss: float | None = None
    validation: dict[str, float] | None = None

    @property
    def steps(self) -> int:
        return self.last_step - self.first_step


@dataclass
class TrainingHistory:
    """All runs that led to a set of weights, oldest first."""

    runs: list[RunRecord] = field(default_factory=list)

    @property
    def total_steps(self) -> int:
        return sum(run.steps for run in self.runs)

    @property
    def total_pairs(self) -> int:
        return sum(run.pairs for run in self.runs)

    @property
    def total_minutes(self) -> float:
        return sum(run.minutes for run in self.runs)

    def to_dict(self) -> dict[str, Any]:
        """The runs plus their totals, as builtins (checkpoint- and JSON-ready)."""
        return {
            "total_steps": self.total_steps,
            "total_pairs": self.total_pairs,
            "total_minutes": self.total_minutes,
            "runs": [asdict(run) for run in self.runs],
        }

    @classmethod
    def from_dict(cls, values: dict[str, Any] | None) -> TrainingHistory:
        """Inverse of `to_dict` (totals are recomputed); None gives an empty history."""
        return cls([RunRecord(**run) for run in values["runs"]]) if values else cls()
