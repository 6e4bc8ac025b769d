"""Export a training checkpoint as a weights file (docs/CONTRACTS.md format), optionally fp16."""

from __future__ import annotations

from pathlib import Path

from crestereo_pp.model.weights import WeightsFile, read_weights, weights_of, write_weights


def export_weights(checkpoint: Path, output: Path, half: bool = False) -> WeightsFile:
    """Write `output`: the checkpoint's weights file (`model.weights.weights_of`: without the
    optimiser, scheduler and RNG states), float16 with `half`. Returns the written payload."""
    payload = weights_of(read_weights(checkpoint), half)
    write_weights(payload, output)
    return payload
