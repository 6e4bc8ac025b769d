"""The OpenVINO backend: the network compiled for the CPU, behind the same forward as torch.

The network is exported once per iteration counts, starting from a given disparity (zeros for a
cold start), with symbolic batch, height and width (``inference.openvino_export``), and the graph
is saved to a disk cache (OpenVINO IR, keyed by the weights' hash and the library versions). Each
padded input shape then gets its own compiled model (a static shape runs about 10 % faster than
the symbolic one), kept in an in-memory cache bounded by shapes and by their estimated memory
(``compiled_bytes``); OpenVINO's own ``CACHE_DIR`` keeps the compiled blobs, so a restart neither
exports nor compiles again. Precision is OpenVINO's inference precision hint: ``f32``, or ``bf16``
where the CPU computes bf16 natively (AVX512-BF16, AMX).

A graph is exported only when asked for (``prepare``; ``crestereo-pp prepare`` from the shell),
never by a call: a call whose graph is neither in memory nor in the disk cache runs on torch in
fp32. An export takes a minute or two of one core (README, "Backends"); it runs in a child process
(watched by a background thread) that ends with the process that started it: side by side with
the others asked for while the caller waits, one at a time in the background.
Its files reach the cache complete, under their final names; partial ones are removed, by the
process that started it or, where that was killed, by the next one to use the cache. A graph
whose export fails runs on torch from then on (logged once).
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import tempfile
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from importlib.util import find_spec
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from .forward import Forward, Maps
from .openvino_export import EXPORT_VERSION, export_in_child, graph_stem, remove_graph
from .options import StageCounts

logger = logging.getLogger(__name__)

BF16_CPU_FLAGS = ("amx_bf16", "avx512_bf16")

COMPILED_BASE_BYTES = 16 << 20
COMPILED_BYTES_PER_ITERATION = 7 << 20
COMPILED_BYTES_PER_PIXEL = {True: (125.0, 4.8), False: (80.0, 7.0)}
"""The estimate of what one compiled shape holds (``compiled_bytes``), fitted from above to the
in-use malloc bytes after its first call: the code and constants of the unrolled graph, which grow
with the iterations it unrolls (lite's 1,1,1: 31-32 MiB, 0,0,6: 48 MiB, 2,4,6: 87-93 MiB at
1x64x96), plus its buffers, which grow with the input pixels (batch x height x width) and with the
network's feature channels C: (a + b x C) bytes a pixel, (a, b) by precision (bf16: True). lite's
2,4,6 (C = 64) at 1x384x1248 and 1x576x1888 took 285-287 and 527-530 MiB in bf16, 310 and 617 MiB
in fp32 (0,0,6: 242 and 475 MiB in bf16); full's 2,4,8 (C = 256) took 711 and 1439 MiB in bf16,
934 and 1981 MiB in fp32: about 415 and 500 bytes a pixel beyond the graph for lite, 1270 and
1800 for full."""

MAX_COMPILED_BYTES = 1856 << 20
"""Default bound of the compiled shapes kept per model, by their estimated memory: the shapes of
one camera's pairs computed by ``two_pass="auto"`` at the largest size it enlarges to (1.2 M
pixels) fit for lite, its quick pass, one pass and both of two passes, in either precision
(600x888 pairs at 1.5x: 1.50 GiB estimated in bf16, 1.75 in fp32; a KITTI frame at 1.5x: 1.35
and 1.57 GiB). full's take about three times as much (4.0 and 5.4 GiB at 600x888): under this
bound full computes such a camera's pairs but compiles some of their shapes again. Under 768 MiB,
the bound before pairs were enlarged, those shapes evicted one another and each request compiled
again: a KITTI pair in two passes at 1.5x took 2.7 s against 1.2 s on a 2-core AVX512-BF16 CPU
(``bench/camera_shapes.py``). Under a mix of many sizes the bound before that, 8 shapes, held
0.9-1.2 GiB, and 8 large ones (4 MP each) would have held about 12 GiB."""

MAX_BLOB_CACHE_BYTES = 512 << 20
"""Default bound of the disk cache of compiled shapes (OpenVINO's ``CACHE_DIR``, shared by the
models and weights using one cache root): each image size a server meets adds a blob of 4-30 MB
(200 MB for a 4 MP pair), so that a client sending many sizes would otherwise fill the disk. Past
the bound the oldest blobs go before the next compile (a size met again compiles once more)."""

_EXPORT_LOCK = threading.Lock()
"""One background export at a time in a process: a service that exports while it serves leaves
the other cores to its requests."""


_CORE_LOCK = threading.Lock()
_core: Any = None


def shared_core() -> Any:
    """The process's one ``openvino.Core``, which every model compiled here shares.

    One, and kept for the process's life: each Core loads a CPU plugin of its own, and the plugin
    gives the thread that first compiles with it an alternate signal stack of its own, and on its
    destruction puts back the stack that thread had before. Two Cores whose models are let go in
    the order they were made (a model loaded again in a notebook, a service's models, a test
    session) leave that thread's signal stack on memory already freed, and the next signal
    handled there (Ctrl-C, or a child's exit with a handler installed) kills the process with
    SIGSEGV."""
    global _core
    with _CORE_LOCK:
        if _core is None:
            import openvino as ov

            _core = ov.Core()
        return _core


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


def graph_folder_name(cache_key: str) -> str:
    """The cache folder of one weights file's graphs (`cache_key`: ``name-hash``): its graphs as
    this torch exports them, at this ``EXPORT_VERSION``."""
    return f"{cache_key}{_version_suffix()}"


def _version_suffix() -> str:
    return f"-torch{torch.__version__}-v{EXPORT_VERSION}"


_GRAPH_FOLDER = re.compile(r"[A-Za-z0-9_]+-[0-9a-f]{16}-torch[^/]+-v[0-9]+")


def other_version_graph_folders(cache_dir: Path | None = None) -> list[Path]:
    """The graph folders in the cache (``cache_dir``, else ``default_cache_dir()``) that this
    install never reads: exported by another torch version or at another ``EXPORT_VERSION`` (an
    update leaves them behind, several MB each). Folders of other weights at this install's
    versions are not among them (a user's own weights may need them)."""
    folder = (cache_dir or default_cache_dir()) / "openvino"
    if not folder.is_dir():
        return []
    return sorted(
        path
        for path in folder.iterdir()
        if path.is_dir() and _GRAPH_FOLDER.fullmatch(path.name) and not path.name.endswith(_version_suffix())
    )


def compiled_bytes(iters: StageCounts, shape: tuple[int, ...], bf16: bool, channels: int) -> int:
    """Estimated memory of the graph for `iters` of a network with `channels` feature channels,
    compiled for input `shape` (B, C, H, W) in bf16 (else fp32), its infer request included."""
    batch, _, height, width = shape
    unrolled = COMPILED_BASE_BYTES + COMPILED_BYTES_PER_ITERATION * sum(iters)
    fixed, per_channel = COMPILED_BYTES_PER_PIXEL[bf16]
    return unrolled + round((fixed + per_channel * channels) * batch * height * width)


@dataclass(frozen=True)
class _Compiled:
    """A model compiled for one input shape and precision, with the one request that runs it."""

    model: Any
    request: Any
    lock: threading.Lock


class OpenVINOForward:
    """A ``Forward`` (see ``inference.forward``) computed by OpenVINO on the CPU.

    network: the eval-mode network to export; channels: its feature channels (``ModelConfig``'s
    feature_dim, for the memory estimate). fallback: the torch forward of calls whose graph is not
    ready (neither in memory nor in the disk cache; ``prepare`` exports it).
    cache_key: names the model and its weights in the disk cache (``name-hash``); None keeps graphs
    in memory only. cache_dir: the cache's root (``default_cache_dir()``); graphs go to its
    ``openvino/graph_folder_name(cache_key)`` folder, blobs to ``openvino/compiled``.
    max_shapes, max_bytes: compiled shapes kept in memory, at most that many and that much
    estimated memory (``compiled_bytes``) together; the least recently used are dropped
    before another is compiled, and one shape larger than `max_bytes` is kept alone.
    Thread-safe: calls may come from several threads. Each export runs in a child process that a
    daemon thread waits for (``prepare``).
    """

    def __init__(
        self,
        network: nn.Module,
        fallback: Forward,
        *,
        channels: int,
        cache_key: str | None,
        cache_dir: Path | None = None,
        max_shapes: int = 8,
        max_bytes: int = MAX_COMPILED_BYTES,
        max_blob_bytes: int = MAX_BLOB_CACHE_BYTES,
    ) -> None:
        if max_shapes < 1:
            raise ValueError(f"max_shapes must be positive, got {max_shapes}")
        self.network = network
        self.channels = channels
        self.fallback = fallback
        self.max_shapes = max_shapes
        self.max_bytes = max_bytes
        self.max_blob_bytes = max_blob_bytes
        directory = (cache_dir or default_cache_dir()) / "openvino"
        self.graph_dir = None if cache_key is None else directory / graph_folder_name(cache_key)
        if self.graph_dir is not None and self.graph_dir.is_dir():
            _remove_abandoned_exports(self.graph_dir)
        self.core = shared_core()
        compiled_dir = directory / "compiled"
        self.blob_dir = compiled_dir if cache_key is not None and _writable(compiled_dir) else None
        self.graphs: dict[StageCounts, Any] = {}
        self.compiled: OrderedDict[tuple[StageCounts, tuple[int, ...], bool], _Compiled] = OrderedDict()
        self.failed: set[StageCounts] = set()
        self.exports = self.compiles = self.runs = self.fallback_runs = 0
        self._pending: dict[StageCounts, threading.Event] = {}  # set when the export has ended
        self._lock = threading.Lock()

    def __call__(self, left: Tensor, right: Tensor, init: Tensor | None, iters: StageCounts, bf16: bool) -> Maps:
        counts: StageCounts = (*iters,)
        with self._lock:
            graph = self._cached(counts)
            if graph is None:
                self.fallback_runs += 1
        if graph is None:
            return self.fallback(left, right, init, iters, False)  # the torch reference, in fp32
        compiled = self._compiled(counts, graph, tuple(left.shape), bf16)
        start = left.new_zeros(left.shape[0], 1, *left.shape[-2:]) if init is None else init  # zeros: a cold start
        inputs = [np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float32) for t in (left, right, start)]
        with compiled.lock:  # one request per compiled shape, reused: a new one allocates every buffer again
            compiled.request.infer(inputs)
            outputs = [compiled.request.get_output_tensor(i).data.copy() for i in (0, 1)]
        disparity, uncertainty = (torch.from_numpy(output) for output in outputs)
        with self._lock:
            self.runs += 1
        return disparity.to(left.device), uncertainty.to(left.device)

    def ready(self, iters: StageCounts) -> bool:
        """Whether calls with these iterations (cold or warm) run on OpenVINO now (their graph in
        memory or in the disk cache, where an export puts its .xml last); starts nothing, reads
        nothing, and takes no lock: the service asks it for every request on its event loop,
        while a compile may hold the lock for seconds."""
        counts: StageCounts = (*iters,)
        path = self._path(counts)
        return counts in self.graphs or (path is not None and path.is_file())

    def prepare(self, graphs: Sequence[StageCounts], *, wait: bool = True) -> bool:
        """Load the graphs for these iterations from the disk cache, else export them: where
        `wait`, side by side (each in a process of its own, which keeps about one core busy) while
        the caller waits for them all; else in the background, one at a time in this process (a
        service exporting while it serves). Returns whether they are all ready (False after a
        failed export: those iterations run on torch)."""
        pending = []
        with self._lock:
            for iters in graphs:
                counts: StageCounts = (*iters,)
                if self._cached(counts) is not None or counts in self.failed:
                    continue
                if counts not in self._pending:
                    self._pending[counts] = threading.Event()
                    # A daemon thread: an export under way never holds up the process's exit (its
                    # child process ends with this process, see ``openvino_export._end_with_parent``).
                    thread = threading.Thread(
                        target=self._export, args=(counts, not wait), name="openvino-export", daemon=True
                    )
                    thread.start()
                pending.append(self._pending[counts])
        if wait:
            for event in pending:
                event.wait()
        return all(self.ready(iters) for iters in graphs)

    def _path(self, counts: StageCounts) -> Path | None:
        return None if self.graph_dir is None else self.graph_dir / f"{graph_stem(counts)}.xml"

    def _cached(self, counts: StageCounts) -> Any | None:
        """The graph for `counts` from memory, else from the disk cache (read into memory); None if
        neither has it. Call with the lock held."""
        if counts not in self.graphs:
            path = self._path(counts)
            if path is None or not path.is_file():
                return None
            self.graphs[counts] = self.core.read_model(path)
            logger.info("openvino: the graph for %s is ready, read from the cache", _described(counts))
        return self.graphs[counts]

    def _export(self, counts: StageCounts, one_at_a_time: bool) -> None:
        with _EXPORT_LOCK if one_at_a_time else contextlib.nullcontext():
            self._export_one(counts)
        with self._lock:
            self._pending.pop(counts).set()

    def _export_one(self, counts: StageCounts) -> None:
        with self._lock:
            if self._cached(counts) is not None:  # exported meanwhile, by another predictor or process
                return
        logger.info(
            "openvino: exporting the graph for %s; its calls run on torch until it is ready", _described(counts)
        )
        start = time.monotonic()
        try:
            graph = self._exported(counts, self._path(counts))
        except Exception:
            logger.exception("openvino: export failed for %s; its calls run on torch", _described(counts))
            with self._lock:
                self.failed.add(counts)
            return
        with self._lock:
            self.graphs[counts] = graph
            self.exports += 1
        logger.info(
            "openvino: the graph for %s is ready, exported in %.0f s; its calls run on OpenVINO from now on",
            _described(counts),
            time.monotonic() - start,
        )

    def _exported(self, counts: StageCounts, path: Path | None) -> Any:
        """The graph for `counts`, exported by a child process straight into the disk cache where it can
        be written (then read from there), else into a temporary folder (kept in memory only)."""
        if path is not None and _writable(path.parent):
            # unique per export (two processes may export the same graph at once), and named by
            # this process, so that a later one can tell the files of an abandoned export
            partial = path.with_name(f".{os.getpid()}-{uuid.uuid4().hex[:8]}-{path.name}")
            try:
                export_in_child(self.network, counts, partial)
                partial.with_suffix(".bin").replace(path.with_suffix(".bin"))
                partial.replace(path)  # the .xml last: a graph on disk is complete
            finally:
                remove_graph(partial)  # nothing left once renamed, or after a failed export
            return self.core.read_model(path)
        if path is not None:
            logger.warning("openvino: %s cannot be written; the graph lives in memory only", path.parent)
        with tempfile.TemporaryDirectory(prefix="crestereo-graph-") as folder:
            graph_file = Path(folder) / "graph.xml"
            export_in_child(self.network, counts, graph_file)
            graph = self.core.read_model(graph_file)
            graph.get_ops()  # read everything now: the folder goes away
            return graph.clone()

    def _compiled(self, counts: StageCounts, graph: Any, shape: tuple[int, ...], bf16: bool) -> _Compiled:
        key = (counts, shape, bf16)
        with self._lock:
            if key in self.compiled:
                self.compiled.move_to_end(key)
                return self.compiled[key]
            # before compiling: the cache and the new one fit the bound
            self._make_room(compiled_bytes(counts, shape, bf16, self.channels))
            if self.blob_dir is not None:
                prune_oldest(self.blob_dir, "*.blob", self.max_blob_bytes)
            static = graph.clone()
            batch, _, height, width = shape
            images, init = [batch, 3, height, width], [batch, 1, height, width]
            static.reshape({port: images if i < 2 else init for i, port in enumerate(static.inputs)})
            blobs = {} if self.blob_dir is None else {"CACHE_DIR": str(self.blob_dir)}
            model = self.core.compile_model(
                static,
                "CPU",
                {
                    "INFERENCE_PRECISION_HINT": "bf16" if bf16 else "f32",
                    "INFERENCE_NUM_THREADS": torch.get_num_threads(),
                    "PERFORMANCE_HINT": "LATENCY",
                    **blobs,
                },
            )
            compiled = _Compiled(model, model.create_infer_request(), threading.Lock())
            self.compiles += 1
            self.compiled[key] = compiled
            return compiled

    @property
    def kept_bytes(self) -> int:
        """Estimated memory of the compiled shapes kept (``compiled_bytes``)."""
        return sum(compiled_bytes(counts, shape, bf16, self.channels) for counts, shape, bf16 in self.compiled)

    def _make_room(self, nbytes: int) -> None:
        """Drop compiled shapes, least recently used first, until one more of `nbytes` fits both
        bounds (all of them where it alone is over `max_bytes`). Call with the lock held; a call
        computing on a dropped shape keeps it until it returns."""
        while self.compiled and (len(self.compiled) >= self.max_shapes or self.kept_bytes + nbytes > self.max_bytes):
            self.compiled.popitem(last=False)


def _described(counts: StageCounts) -> str:
    return f"iterations {counts}"


def prune_oldest(folder: Path, pattern: str, max_bytes: int) -> int:
    """Delete the files of `folder` matching `pattern`, least recently modified first, until they
    take at most `max_bytes` together; files that another process deletes meanwhile are skipped.
    Returns the bytes deleted."""
    files = []
    for path in folder.glob(pattern):
        try:
            stat = path.stat()
        except FileNotFoundError:
            continue
        files.append((stat.st_mtime, stat.st_size, path))
    files.sort()
    total = sum(size for _, size, _ in files)
    deleted = 0
    for _, size, path in files:
        if total - deleted <= max_bytes:
            break
        try:
            path.unlink()
        except FileNotFoundError:
            pass
        deleted += size
    return deleted


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
