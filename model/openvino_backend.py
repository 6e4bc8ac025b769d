"""The OpenVINO backend: the network compiled for the CPU, behind the same forward as torch.

The network is exported once per iteration counts and start (cold, or warm from a given
disparity) with symbolic batch, height and width (torch's ONNX exporter, then
``openvino.convert_model``), and the graph is saved to a disk cache (OpenVINO IR, keyed by the
weights' hash and the library versions). Each padded input shape then gets its own compiled
model (a static shape runs about 10 % faster than the symbolic one), kept in a bounded in-memory
cache; OpenVINO's own ``CACHE_DIR`` keeps the compiled blobs, so a restart neither exports nor
compiles again. Precision is OpenVINO's inference precision hint: ``f32``, or ``bf16`` where the
CPU computes bf16 natively (AVX512-BF16, AMX).

A graph is exported only when asked for (``prepare``; ``crestereo-pp prepare`` from the shell),
never by a call: a call whose graph is neither in memory nor in the disk cache runs on torch in
fp32. An export takes minutes of CPU (README, "Benchmarks"); it runs in a child process (one at a
time per process, watched by a background thread) that ends with the process that started it.
Its files reach the cache complete, under their final names; partial ones are removed, by the
process that started it or, where that was killed, by the next one to use the cache. A graph
whose export fails runs on torch from then on (logged once).
"""

from __future__ import annotations

import ctypes
import io
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
import uuid
import warnings
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from importlib.util import find_spec
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from .cuda_graphs import Forward, Maps, put_bounded
from .network import INPUT_MULTIPLE
from .options import StageCounts

logger = logging.getLogger(__name__)

EXPORT_VERSION = 5
"""Bumped whenever the exported graph changes for the same weights (part of the cache key)."""

MAX_BATCH = 64
MAX_SIDE = 8192
"""Largest batch and padded side (px) an exported graph accepts."""

BF16_CPU_FLAGS = ("amx_bf16", "avx512_bf16")

PR_SET_PDEATHSIG = 1
"""Linux's prctl option: the signal a process gets when the thread that started it ends."""

_EXPORT_LOCK = threading.Lock()
"""One export at a time in a process: each keeps every core busy for minutes."""


def openvino_available() -> bool:
    """Whether the ``openvino`` package can be imported."""
    return find_spec("openvino") is not None


def native_bf16(cpuinfo: Path = Path("/proc/cpuinfo")) -> bool:
    """Whether this CPU computes bf16 natively (AMX or AVX512-BF16), from the kernel's flags."""
    try:
        text = cpuinfo.read_text()
    except OSError:
        return False
    flags = {flag for line in text.splitlines() if line.startswith("flags") for flag in line.split(":", 1)[1].split()}
    return any(flag in flags for flag in BF16_CPU_FLAGS)


def default_cache_dir() -> Path:
    """Where the project's caches live: ``$CRESTEREO_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/crestereo-pp``, else ``~/.cache/crestereo-pp``."""
    root = os.environ.get("CRESTEREO_CACHE_DIR")
    if root:
        return Path(root)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "crestereo-pp"


@dataclass(frozen=True)
class GraphKind:
    """What an exported graph computes: the iterations per stage (1/16, 1/8, 1/4) and whether it
    starts warm from a given disparity (an extra input)."""

    iters: StageCounts
    warm_start: bool

    @property
    def file_stem(self) -> str:
        n16, n8, n4 = self.iters
        return f"iters{n16}-{n8}-{n4}-{'warm' if self.warm_start else 'cold'}"


@dataclass(frozen=True)
class _Compiled:
    """A model compiled for one input shape and precision, with the one request that runs it."""

    model: Any
    request: Any
    lock: threading.Lock


class _Graph(nn.Module):
    """The module that is exported: the network at fixed iterations, maps in float32."""

    def __init__(self, network: nn.Module, iters: StageCounts) -> None:
        super().__init__()
        self.network = network
        self.iters = iters

    def forward(self, left: Tensor, right: Tensor, init: Tensor | None = None) -> Maps:
        out = self.network(left, right, iters=self.iters, init_disparity=init)
        return out.disparity.float(), out.uncertainty.float()


def export_graph(network: nn.Module, kind: GraphKind, onnx_file: Path) -> Any:
    """The network as an ``openvino.Model`` with symbolic batch, height and width (multiples of
    INPUT_MULTIPLE): inputs left, right (B, 3, H, W) float32 in [0, 255] and, warm, init
    (B, 1, H, W) px; outputs disparity and uncertainty (B, 1, H, W) float32.

    Through ONNX (torch's dynamo exporter, which also simplifies the graph), written to
    `onnx_file` meanwhile: the graph OpenVINO builds from it ran 15-20 % faster than one converted
    from ``torch.export`` directly."""
    import openvino as ov

    batch = torch.export.Dim("batch", min=1, max=MAX_BATCH)
    rows = torch.export.Dim("rows", min=1, max=MAX_SIDE // INPUT_MULTIPLE)
    columns = torch.export.Dim("columns", min=1, max=MAX_SIDE // INPUT_MULTIPLE)
    sizes = {0: batch, 2: INPUT_MULTIPLE * rows, 3: INPUT_MULTIPLE * columns}
    # Batch 2 and distinct tensors: an example of size 1, or one tensor passed twice, would be specialised.
    left = torch.full((2, 3, 2 * INPUT_MULTIPLE, 4 * INPUT_MULTIPLE), 128.0)
    inputs: tuple[Tensor, ...] = (left, left + 1.0)
    names = ["left", "right"]
    if kind.warm_start:
        inputs = (*inputs, torch.full((2, 1, *left.shape[-2:]), 4.0))
        names.append("init")
    quiet = logging.getLogger("torch.onnx")  # notes about torchvision operators this network does not use
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the exporter's own deprecation notices, not ours
            program = torch.onnx.export(
                _Graph(network, kind.iters).eval(),
                inputs,
                dynamo=True,
                opset_version=18,
                input_names=names,
                output_names=["disparity", "uncertainty"],
                dynamic_shapes=tuple(sizes for _ in inputs),
                verbose=False,
            )
    finally:
        quiet.setLevel(level)
    assert program is not None  # dynamo=True always returns the program
    try:
        program.save(str(onnx_file))
        return ov.convert_model(onnx_file)
    finally:
        onnx_file.unlink(missing_ok=True)


class OpenVINOForward:
    """A ``Forward`` (see ``model.cuda_graphs``) computed by OpenVINO on the CPU.

    network: the eval-mode network to export. fallback: the torch forward of calls whose graph is
    not ready (neither in memory nor in the disk cache; ``prepare`` exports it).
    cache_key: names these weights in the disk cache (their hash); None keeps graphs in memory
    only. cache_dir: the cache's root (``default_cache_dir()``); graphs and blobs go to its
    ``openvino/`` folder. max_shapes: compiled shapes kept in memory (least recently used dropped first).
    Thread-safe: calls may come from several threads; one export runs at a time, in a child
    process that a daemon thread waits for.
    """

    def __init__(
        self,
        network: nn.Module,
        fallback: Forward,
        *,
        cache_key: str | None,
        cache_dir: Path | None = None,
        max_shapes: int = 8,
    ) -> None:
        import openvino as ov

        if max_shapes < 1:
            raise ValueError(f"max_shapes must be positive, got {max_shapes}")
        self.network = network
        self.fallback = fallback
        self.max_shapes = max_shapes
        directory = (cache_dir or default_cache_dir()) / "openvino"
        self.graph_dir = None if cache_key is None else directory / f"{cache_key}-v{EXPORT_VERSION}"
        if self.graph_dir is not None and self.graph_dir.is_dir():
            _remove_abandoned_exports(self.graph_dir)
        self.core = ov.Core()
        compiled_dir = directory / "compiled"
        if cache_key is not None and _writable(compiled_dir):
            self.core.set_property({"CACHE_DIR": str(compiled_dir)})
        self.graphs: dict[GraphKind, Any] = {}
        self.compiled: OrderedDict[tuple[GraphKind, tuple[int, ...], bool], _Compiled] = OrderedDict()
        self.failed: set[GraphKind] = set()
        self.exports = self.compiles = self.runs = self.fallback_runs = 0
        self._pending: dict[GraphKind, threading.Event] = {}  # set when the export has ended
        self._lock = threading.Lock()

    def __call__(self, left: Tensor, right: Tensor, init: Tensor | None, iters: StageCounts, bf16: bool) -> Maps:
        kind = GraphKind((*iters,), init is not None)
        with self._lock:
            graph = self._cached(kind)
            if graph is None:
                self.fallback_runs += 1
        if graph is None:
            return self.fallback(left, right, init, iters, False)  # the torch reference, in fp32
        compiled = self._compiled(kind, graph, tuple(left.shape), bf16)
        given = (left, right) if init is None else (left, right, init)
        inputs = [np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float32) for t in given]
        with compiled.lock:  # one request per compiled shape, reused: a new one allocates every buffer again
            compiled.request.infer(inputs)
            outputs = [compiled.request.get_output_tensor(i).data.copy() for i in (0, 1)]
        disparity, uncertainty = (torch.from_numpy(output) for output in outputs)
        with self._lock:
            self.runs += 1
        return disparity.to(left.device), uncertainty.to(left.device)

    def ready(self, iters: StageCounts, warm_start: bool = False) -> bool:
        """Whether calls of this kind run on OpenVINO now (its graph in memory or in the disk
        cache); starts nothing."""
        with self._lock:
            return self._cached(GraphKind((*iters,), warm_start)) is not None

    def prepare(self, iters: StageCounts, warm_start: bool = False, *, wait: bool = True) -> bool:
        """Load the graph of this kind from the disk cache, else export it (in the background
        unless `wait`); returns whether it is ready (False after a failed export: that kind runs
        on torch)."""
        kind = GraphKind((*iters,), warm_start)
        with self._lock:
            if self._cached(kind) is not None:
                return True
            if kind not in self.failed and kind not in self._pending:
                self._pending[kind] = threading.Event()
                # A daemon thread: an export under way never holds up the process's exit (its
                # child process ends with this process, see _end_with_parent).
                thread = threading.Thread(target=self._export, args=(kind,), name="openvino-export", daemon=True)
                thread.start()
            pending = self._pending.get(kind)
        if wait and pending is not None:
            pending.wait()
        return self.ready(iters, warm_start)

    def _path(self, kind: GraphKind) -> Path | None:
        return None if self.graph_dir is None else self.graph_dir / f"{kind.file_stem}.xml"

    def _cached(self, kind: GraphKind) -> Any | None:
        """The kind's graph from memory, else from the disk cache (read into memory); None if
        neither has it. Call with the lock held."""
        if kind not in self.graphs:
            path = self._path(kind)
            if path is None or not path.is_file():
                return None
            self.graphs[kind] = self.core.read_model(path)
            logger.info("openvino: the graph for %s is ready, read from the cache", _described(kind))
        return self.graphs[kind]

    def _export(self, kind: GraphKind) -> None:
        with _EXPORT_LOCK:
            self._export_one(kind)
        with self._lock:
            self._pending.pop(kind).set()

    def _export_one(self, kind: GraphKind) -> None:
        with self._lock:
            if self._cached(kind) is not None:  # exported meanwhile, by another predictor or process
                return
        logger.info("openvino: exporting the graph for %s; its calls run on torch until it is ready", _described(kind))
        start = time.monotonic()
        try:
            graph = self._exported(kind, self._path(kind))
        except Exception:
            logger.exception("openvino: export failed for %s; its calls run on torch", _described(kind))
            with self._lock:
                self.failed.add(kind)
            return
        with self._lock:
            self.graphs[kind] = graph
            self.exports += 1
        logger.info(
            "openvino: the graph for %s is ready, exported in %.0f s; its calls run on OpenVINO from now on",
            _described(kind),
            time.monotonic() - start,
        )

    def _exported(self, kind: GraphKind, path: Path | None) -> Any:
        """The kind's graph, exported by a child process straight into the disk cache where it can
        be written (then read from there), else into a temporary folder (kept in memory only)."""
        if path is not None and _writable(path.parent):
            # unique per export (two processes may export the same graph at once), and named by
            # this process, so that a later one can tell the files of an abandoned export
            partial = path.with_name(f".{os.getpid()}-{uuid.uuid4().hex[:8]}-{path.name}")
            try:
                _export_in_child(self.network, kind, partial)
                partial.with_suffix(".bin").replace(path.with_suffix(".bin"))
                partial.replace(path)  # the .xml last: a graph on disk is complete
            finally:
                _remove_graph(partial)  # nothing left once renamed, or after a failed export
            return self.core.read_model(path)
        if path is not None:
            logger.warning("openvino: %s cannot be written; the graph lives in memory only", path.parent)
        with tempfile.TemporaryDirectory(prefix="crestereo-graph-") as folder:
            graph_file = Path(folder) / "graph.xml"
            _export_in_child(self.network, kind, graph_file)
            graph = self.core.read_model(graph_file)
            graph.get_ops()  # read everything now: the folder goes away
            return graph.clone()

    def _compiled(self, kind: GraphKind, graph: Any, shape: tuple[int, ...], bf16: bool) -> _Compiled:
        key = (kind, shape, bf16)
        with self._lock:
            if key in self.compiled:
                self.compiled.move_to_end(key)
                return self.compiled[key]
            static = graph.clone()
            batch, _, height, width = shape
            images, init = [batch, 3, height, width], [batch, 1, height, width]
            static.reshape({port: images if i < 2 else init for i, port in enumerate(static.inputs)})
            model = self.core.compile_model(
                static,
                "CPU",
                {
                    "INFERENCE_PRECISION_HINT": "bf16" if bf16 else "f32",
                    "INFERENCE_NUM_THREADS": torch.get_num_threads(),
                    "PERFORMANCE_HINT": "LATENCY",
                },
            )
            compiled = _Compiled(model, model.create_infer_request(), threading.Lock())
            self.compiles += 1
            put_bounded(self.compiled, key, compiled, self.max_shapes)
            return compiled


def _described(kind: GraphKind) -> str:
    return f"iterations {kind.iters} ({'warm' if kind.warm_start else 'cold'} start)"


def _export_in_child(network: nn.Module, kind: GraphKind, graph_file: Path) -> None:
    """`export_graph` in a child process (``python -m crestereo_pp.model.openvino_backend``), saved as
    OpenVINO IR at `graph_file` (.xml, with its .bin beside it). The network reaches it through
    its standard input: no file of it is left behind, however this process ends.

    Not in a thread of this process: the exporter traces the network under torch's dispatch modes
    (fake tensors, functionalisation), which other threads running the network would meet too."""
    network_bytes = io.BytesIO()
    torch.save(network, network_bytes)
    n16, n8, n4 = kind.iters
    command = [
        sys.executable,
        "-m",
        "crestereo_pp.model.openvino_backend",
        str(os.getpid()),
        str(n16),
        str(n8),
        str(n4),
    ]
    command += ["warm" if kind.warm_start else "cold", str(graph_file)]
    done = subprocess.run(command, input=network_bytes.getvalue(), capture_output=True, check=False)
    if done.returncode != 0:
        error = done.stderr.decode(errors="replace")[-2000:]
        raise RuntimeError(f"the export process failed ({done.returncode}): {error}")


def _export_main(arguments: Sequence[str]) -> None:
    """The export process: PARENT_PID N16 N8 N4 cold|warm GRAPH_XML, the network on stdin. Its
    files (the .xml and .bin, the .onnx meanwhile) are named after GRAPH_XML."""
    parent, n16, n8, n4, start, graph_file = arguments
    _end_with_parent(int(parent))
    # Read before openvino is imported: its telemetry forks a process from another thread, and a
    # process forked while this thread holds stdin's lock hangs as it closes stdin.
    network_bytes = sys.stdin.buffer.read()
    import openvino as ov

    network = torch.load(io.BytesIO(network_bytes), weights_only=False)  # from the parent, just now
    xml = Path(graph_file)
    graph = export_graph(network, GraphKind((int(n16), int(n8), int(n4)), start == "warm"), xml.with_suffix(".onnx"))
    ov.save_model(graph, xml, compress_to_fp16=False)


def _end_with_parent(parent: int) -> None:
    """Have the kernel kill this process when the thread that started it ends (Linux's
    PR_SET_PDEATHSIG; that thread waits for this process, so it ends first only when its whole
    process ends, by exit or by signal); end now if the parent has already ended. Files this
    process leaves are its parent's partial files (see _remove_abandoned_exports)."""
    if sys.platform == "linux":
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    if os.getppid() != parent:
        raise SystemExit("the process that asked for this export has ended")


def _remove_graph(xml: Path) -> None:
    """Remove the files of a graph, where they exist: .xml, .bin and the .onnx of its export."""
    for suffix in (".xml", ".bin", ".onnx"):
        xml.with_suffix(suffix).unlink(missing_ok=True)


def _remove_abandoned_exports(folder: Path) -> None:
    """Remove the partial files (``.PID-...``) of exports whose process has ended before renaming
    or removing them (killed: its export process was killed with it)."""
    for path in folder.glob(".*-iters*"):
        pid = path.name[1:].split("-", 1)[0]
        if pid.isdigit() and not _running(int(pid)):
            path.unlink(missing_ok=True)


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # it exists, as another user's
        pass
    return True


def _writable(directory: Path) -> bool:
    """Whether `directory` exists or can be made, and files can be written in it."""
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    return os.access(directory, os.W_OK)


if __name__ == "__main__":
    _export_main(sys.argv[1:])
