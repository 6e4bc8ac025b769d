"""The OpenVINO export: the network as an OpenVINO graph with symbolic batch, height and width,
computed in a child process of its own (``python -m crestereo_pp.inference.openvino_export``).

One graph per iteration counts, starting from a given disparity (a cold start gives zeros, which
is what the network starts from without one): torch's ONNX exporter, then
``openvino.convert_model``. The child process reads the network from its standard input, writes
the graph as OpenVINO IR (.xml and .bin) and ends with the process that started it;
``inference.openvino_backend`` decides when to export and keeps the graphs in its cache.
"""

from __future__ import annotations

import ctypes
import io
import logging
import os
import signal
import subprocess
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from crestereo_pp.model.network import INPUT_MULTIPLE

from .forward import Maps
from .onnx_optimize import optimize_onnx
from .options import StageCounts

EXPORT_VERSION = 8
"""Bumped whenever the exported graph changes for the same weights (part of the cache key). 8: one
graph per iteration counts, for cold and warm starts alike (7 had a cold graph beside the warm)."""

KEEP_FP32 = "precise_0"
"""The runtime-info name of OpenVINO's mark that keeps an op in its own precision
(``ov::disable_fp16_compression``): the CPU plugin honours it under a bf16 inference precision too,
and the IR keeps it (as ``DisablePrecisionConversion``)."""

BF16_OPS = frozenset({"Convolution", "GroupConvolution", "MatMul"})
"""The ops that run in bf16 everywhere under a bf16 inference precision (``keep_features_in_fp32``)."""

CORRELATION_SAMPLING = "GridSample"
"""The op that samples the right image's features at the disparities tried: the iterations start there."""

MAX_BATCH = 64
MAX_SIDE = 8192
"""Largest batch and padded side (px) an exported graph accepts."""

PR_SET_PDEATHSIG = 1
"""Linux's prctl option: the signal a process gets when the thread that started it ends."""


def graph_stem(iters: StageCounts) -> str:
    """The file name (without suffix) of the graph for `iters` in the disk cache."""
    n16, n8, n4 = iters
    return f"iters{n16}-{n8}-{n4}"


class _Graph(nn.Module):
    """The module that is exported: the network at fixed iterations from a start disparity, maps
    in float32."""

    def __init__(self, network: nn.Module, iters: StageCounts) -> None:
        super().__init__()
        self.network = network
        self.iters = iters

    def forward(self, left: Tensor, right: Tensor, init: Tensor) -> Maps:
        out = self.network(left, right, iters=self.iters, init_disparity=init)
        return out.disparity.float(), out.uncertainty.float()


def export_graph(network: nn.Module, iters: StageCounts, onnx_file: Path) -> Any:
    """The network at `iters` as an ``openvino.Model`` with symbolic batch, height and width
    (multiples of INPUT_MULTIPLE): inputs left, right (B, 3, H, W) float32 in [0, 255] and init
    (B, 1, H, W) px, the start disparity (zeros for a cold start: the same maps as a graph without
    the input, to 0.0006 px in fp32, in the same time); outputs disparity and uncertainty
    (B, 1, H, W) float32.

    Through ONNX (torch's dynamo exporter, the graph simplified by ``optimize_onnx``), written to
    `onnx_file` meanwhile: the graph OpenVINO builds from it ran 15-20 % faster than one converted
    from ``torch.export`` directly."""
    import openvino as ov

    batch = torch.export.Dim("batch", min=1, max=MAX_BATCH)
    rows = torch.export.Dim("rows", min=1, max=MAX_SIDE // INPUT_MULTIPLE)
    columns = torch.export.Dim("columns", min=1, max=MAX_SIDE // INPUT_MULTIPLE)
    sizes = {0: batch, 2: INPUT_MULTIPLE * rows, 3: INPUT_MULTIPLE * columns}
    # Batch 2 and distinct tensors: an example of size 1, or one tensor passed twice, would be specialised.
    left = torch.full((2, 3, 2 * INPUT_MULTIPLE, 4 * INPUT_MULTIPLE), 128.0)
    inputs = (left, left + 1.0, torch.full((2, 1, *left.shape[-2:]), 4.0))
    names = ["left", "right", "init"]
    quiet = logging.getLogger("torch.onnx")  # notes about torchvision operators this network does not use
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the exporter's own deprecation notices, not ours
            program = torch.onnx.export(
                _Graph(network, iters).eval(),
                inputs,
                dynamo=True,
                opset_version=18,
                input_names=names,
                output_names=["disparity", "uncertainty"],
                dynamic_shapes=tuple(sizes for _ in inputs),
                verbose=False,
                optimize=False,  # optimize_onnx: the same passes, faster
            )
    finally:
        quiet.setLevel(level)
    assert program is not None  # dynamo=True always returns the program
    optimize_onnx(program.model)
    try:
        program.save(str(onnx_file))
        graph = ov.convert_model(onnx_file)
    finally:
        onnx_file.unlink(missing_ok=True)
    keep_features_in_fp32(graph)
    return graph


def keep_features_in_fp32(graph: Any) -> None:
    """Mark the feature and context networks' ops other than convolutions (their normalisations,
    activations, sums and concatenations: every op that runs before the first correlation
    sampling, not downstream of one) to compute in fp32 where the graph is compiled for bf16; the
    convolutions, and the iterations from the first sampling on, stay in bf16. A compile in fp32
    is unchanged.

    On the dev pairs (default inference, OpenVINO on an AMX CPU) this takes bf16 from 9.12 % bad-2
    and 1.087 px EPE to 8.91 % and 1.073 px (torch fp32: 8.87 % and 1.068 px) at 10 % more time
    (0.76 against 0.69 s a pair, runs alternated); every op but the convolutions in fp32 gave
    8.86 % at 48 % more, and the iterations' ops alone in fp32 changed nothing (model card, "bf16
    with the feature networks' other ops in fp32")."""
    iterations: set[str] = set()  # ops by their unique names: the Python objects are made anew per access
    stack = [op for op in graph.get_ops() if op.get_type_name() == CORRELATION_SAMPLING]
    while stack:
        op = stack.pop()
        if op.get_name() in iterations:
            continue
        iterations.add(op.get_name())
        stack += [target.get_node() for output in op.outputs() for target in output.get_target_inputs()]
    for op in graph.get_ops():
        kind = op.get_type_name()
        if op.get_name() not in iterations and kind not in BF16_OPS and kind not in ("Constant", "Parameter", "Result"):
            op.get_rt_info()[KEEP_FP32] = ""


def export_in_child(network: nn.Module, iters: StageCounts, graph_file: Path) -> None:
    """`export_graph` in a child process (``python -m crestereo_pp.inference.openvino_export``), saved as
    OpenVINO IR at `graph_file` (.xml, with its .bin beside it). The network reaches it through
    its standard input: no file of it is left behind, however this process ends.

    Not in a thread of this process: the exporter traces the network under torch's dispatch modes
    (fake tensors, functionalisation), which other threads running the network would meet too."""
    network_bytes = io.BytesIO()
    torch.save(network, network_bytes)
    n16, n8, n4 = iters
    module = "crestereo_pp.inference.openvino_export"
    command = [sys.executable, "-m", module, str(os.getpid()), str(n16), str(n8), str(n4), str(graph_file)]
    done = subprocess.run(command, input=network_bytes.getvalue(), capture_output=True, check=False)
    if done.returncode != 0:
        error = done.stderr.decode(errors="replace")[-2000:]
        raise RuntimeError(f"the export process failed ({done.returncode}): {error}")


def _export_main(arguments: Sequence[str]) -> None:
    """The export process: PARENT_PID N16 N8 N4 GRAPH_XML, the network on stdin. Its
    files (the .xml and .bin, the .onnx meanwhile) are named after GRAPH_XML."""
    parent, n16, n8, n4, graph_file = arguments
    _end_with_parent(int(parent))
    # Read before openvino is imported: its telemetry forks a process from another thread, and a
    # process forked while this thread holds stdin's lock hangs as it closes stdin.
    network_bytes = sys.stdin.buffer.read()
    import openvino as ov

    network = torch.load(io.BytesIO(network_bytes), weights_only=False)  # from the parent, just now
    xml = Path(graph_file)
    graph = export_graph(network, (int(n16), int(n8), int(n4)), xml.with_suffix(".onnx"))
    ov.save_model(graph, xml, compress_to_fp16=False)


def _end_with_parent(parent: int) -> None:
    """Have the kernel kill this process when the thread that started it ends (Linux's
    PR_SET_PDEATHSIG; that thread waits for this process, so it ends first only when its whole
    process ends, by exit or by signal); end now if the parent has already ended. Files this
    process leaves are its parent's partial files (see ``openvino_backend._remove_abandoned_exports``)."""
    if sys.platform == "linux":
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    if os.getppid() != parent:
        raise SystemExit("the process that asked for this export has ended")


def remove_graph(xml: Path) -> None:
    """Remove the files of a graph, where they exist: .xml, .bin and the .onnx of its export."""
    for suffix in (".xml", ".bin", ".onnx"):
        xml.with_suffix(suffix).unlink(missing_ok=True)


if __name__ == "__main__":
    _export_main(sys.argv[1:])
