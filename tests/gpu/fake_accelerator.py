"""Stand-ins for an accelerator on the CPU: the "meta" device with every host<->device copy
recorded (`DeviceTransfers`), and a "capture" that replays eagerly (`replay_eagerly`).

Tensors on "meta" have shapes and dtypes but no data, so code that runs there end to end can
only have kept its tensors on the device; a copy from the device to the host is where data would
leave it. Inside `DeviceTransfers`, such a copy is recorded and answered with zeros of the right
shape (the meta device's "data"), and so is a read of a device scalar (`.item()`: a host sync on
a GPU); copies from the host to the device are recorded and done.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor
from torch.utils._python_dispatch import TorchDispatchMode

aten = torch.ops.aten
DEVICE = torch.device("meta")


class DeviceTransfers(TorchDispatchMode):
    """Counts, while active: `uploads` (host -> meta copies), `downloads` (meta -> host copies,
    their shapes in `download_shapes`) and `scalar_reads` (.item() of a meta tensor)."""

    def __init__(self) -> None:
        super().__init__()
        self.uploads = 0
        self.downloads = 0
        self.scalar_reads = 0
        self.download_shapes: list[tuple[int, ...]] = []

    def __torch_dispatch__(self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        kwargs = kwargs or {}
        if func is aten._local_scalar_dense.default and args[0].device == DEVICE:
            self.scalar_reads += 1
            return 0
        if func.overloadpacket in (aten._to_copy, aten.to):  # .to(...), .cpu() (aten.to in inference mode)
            source, target = args[0].device, target_device(args, kwargs)
            if source == DEVICE and target.type == "cpu":
                dtype = kwargs.get("dtype") or next((a for a in args if isinstance(a, torch.dtype)), args[0].dtype)
                return self._download(args[0], dtype)
            self.uploads += source.type == "cpu" and target == DEVICE
        if func is aten.copy_.default:
            destination, source = args[0], args[1]
            if source.device == DEVICE and destination.device.type == "cpu":
                self._download(source, source.dtype)
                return destination.zero_()
            self.uploads += source.device.type == "cpu" and destination.device == DEVICE and source.dim() > 0
        return func(*args, **kwargs)

    def _download(self, tensor: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        self.downloads += 1
        self.download_shapes.append(tuple(tensor.shape))
        return torch.zeros(tensor.shape, dtype=dtype)


def target_device(args: tuple, kwargs: dict) -> torch.device:
    """Where an aten.to / aten._to_copy call copies its tensor (args[0]) to."""
    given = kwargs.get("device") or next((a for a in args[1:] if isinstance(a, torch.device)), None)
    return torch.device(given) if given is not None else args[0].device


def replay_eagerly(
    run: Callable[[], tuple[Tensor, Tensor]], device: torch.device
) -> tuple[Callable[[], None], tuple[Tensor, Tensor]]:
    """`inference.cuda_graphs.capture_cuda_graph` without CUDA: `replay()` reruns `run` and writes
    its results into the first run's output tensors, as a graph replay rewrites its outputs."""
    outputs = run()

    def replay() -> None:
        for static, fresh in zip(outputs, run(), strict=True):
            static.copy_(fresh)

    return replay, outputs
