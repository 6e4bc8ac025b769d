"""Which torch device a run uses, from the names the CLI, the service and training configs take."""

from __future__ import annotations

import torch


def resolve_device(name: str, local_rank: int) -> torch.device:
    """ "auto" is cuda:LOCAL_RANK when CUDA is available, else cpu; "cuda" also takes LOCAL_RANK.
    Asking for CUDA where torch has none (a checkpoint trained on a GPU, resumed on a CPU), or for
    a name that is no device, is a ValueError that says what to pass instead."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ValueError(f"device {name!r} is not a torch device: use 'auto', 'cpu', 'cuda' or 'cuda:N'") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {name!r} was asked for, but CUDA is not available here: use 'auto' or 'cpu'")
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", local_rank)
    return device
