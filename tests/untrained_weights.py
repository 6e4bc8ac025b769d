"""A weights file of untrained weights, as a user might pass one: the network's own random
initialisation, with the training record of a short run whose validation on real pairs failed."""

from pathlib import Path

import torch

from crestereo_pp.model import CREStereoPP, ModelConfig
from crestereo_pp.model.weights import write_weights

UNTRAINED_BAD2 = 94.4
"""The recorded dev bad-2 (%) of the file: what an untrained full measured (a run of 600 pairs)."""


def write_untrained(path: Path, name: str = "full") -> Path:
    """Write `name`'s untrained weights file at `path` (seeded, so the same every time); `path`."""
    torch.manual_seed(0)
    network = CREStereoPP(ModelConfig.preset(name))
    validation = {"epe": 26.6, "bad1": 97.2, "bad2": UNTRAINED_BAD2, "bad3": 91.6, "d1_all": 91.6}
    run = {
        "started": "2026-11-23T06:37:56+00:00",
        "origin": "scratch",
        "model": name,
        "device": "cpu",
        "processes": 1,
        "first_step": 0,
        "last_step": 300,
        "pairs": 600,
        "minutes": 17.0,
        "final_loss": 33.3,
        "validation": validation,
    }
    training = {"total_steps": 300, "total_pairs": 600, "total_minutes": 17.0, "runs": [run]}
    payload = {"model": network.state_dict(), "config": network.config.to_dict(), "model_name": name}
    write_weights({**payload, "training": training, "step": 300}, path)
    return path
