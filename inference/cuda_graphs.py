"""The inference forward replayed from CUDA graphs: one graph per padded input shape and options.

A pass of the network is hundreds of small kernels (the authors' Lite code took 54.6 ms per pass
at 384x1248 on an H100, 17.5 ms of it in kernels: the rest is launching them), so
``StereoPredictor.predict_pairs`` (``predict_batch``, the service's batches) on a CUDA device
runs its forward through ``GraphedForward``:
the first call of a key runs eagerly, the next one captures a graph (static input buffers,
warm-up on a side stream, capture) and every later call copies its inputs into the static
buffers, replays the graph with one launch and copies the outputs out: no host allocation, no
per-kernel launches. Only ``capture_cuda_graph`` touches the CUDA graph API; everything else
(keys, buffer reuse, the cache bound, the eager fallback) runs on any device with another capture
function.
"""

from __future__ import annotations

import threading
import warnings
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import torch
from torch import Tensor

from .forward import Forward, Maps
from .options import StageCounts

Capture = Callable[[Callable[[], Maps], torch.device], tuple[Callable[[], None], Maps]]
"""capture(run, device) -> (replay, outputs): record `run` (which reads fixed input buffers on
`device`) so that each `replay()` recomputes it into the same `outputs` tensors."""

WARMUP_RUNS = 2
"""Eager runs on a side stream before a capture (lazy initialisation, cuDNN algorithm choice)."""

Key = TypeVar("Key")
Value = TypeVar("Value")


@dataclass(frozen=True)
class GraphKey:
    """What a captured graph is valid for: the padded input shape (B, 3, H, W), whether a
    warm-start disparity is given, the iterations per stage and bf16 autocast."""

    shape: tuple[int, ...]
    warm_start: bool
    iters: StageCounts
    bf16: bool


@dataclass(frozen=True)
class CapturedGraph:
    """A graph and the buffers it reads and writes: inputs are copied into `left`, `right` (and
    `init`) before each `replay()`, which rewrites `outputs` in place."""

    left: Tensor
    right: Tensor
    init: Tensor | None
    replay: Callable[[], None]
    outputs: Maps


def capture_cuda_graph(run: Callable[[], Maps], device: torch.device) -> tuple[Callable[[], None], Maps]:
    """Capture `run` in a CUDA graph on `device` after WARMUP_RUNS eager runs on a side stream
    (the pattern of the PyTorch CUDA-graph notes). Returns the graph's replay and its output
    tensors; the outputs hold garbage until the first replay."""
    with torch.cuda.device(device):
        side = torch.cuda.Stream()  # type: ignore[no-untyped-call]  # torch leaves it unannotated
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            for _ in range(WARMUP_RUNS):
                run()
        torch.cuda.current_stream().wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph, capture_error_mode="thread_local"):
            outputs = run()
    return graph.replay, outputs


class GraphedForward:
    """`forward` with CUDA-graph replay, callable like `forward` (see ``Forward``).

    A key (``GraphKey``) runs eagerly until it has been seen `capture_after` times, then it is
    captured; at most `max_graphs` graphs are kept (least recently used dropped first, which
    frees their memory pool). A key whose capture raises is warned about once and runs eagerly
    from then on. Results are fresh tensors (copies of the graph's outputs), so they stay valid
    after later calls; calls are serialised by a lock, so threads can share one instance.
    """

    def __init__(
        self,
        forward: Forward,
        *,
        max_graphs: int = 8,
        capture_after: int = 2,
        capture: Capture = capture_cuda_graph,
    ) -> None:
        if max_graphs < 1 or capture_after < 1:
            raise ValueError(f"max_graphs and capture_after must be positive, got {max_graphs} and {capture_after}")
        self.forward = forward
        self.max_graphs = max_graphs
        self.capture_after = capture_after
        self.capture = capture
        self.graphs: OrderedDict[GraphKey, CapturedGraph] = OrderedDict()
        self.sightings: OrderedDict[GraphKey, int] = OrderedDict()  # keys not captured yet
        self.uncapturable: OrderedDict[GraphKey, None] = OrderedDict()
        self.captures = self.replays = self.eager_runs = 0
        self._lock = threading.Lock()

    def __call__(self, left: Tensor, right: Tensor, init: Tensor | None, iters: StageCounts, bf16: bool) -> Maps:
        key = GraphKey(tuple(left.shape), init is not None, (*iters,), bf16)
        with self._lock:
            graph = self._graph_for(key, left, right, init)
            if graph is None:
                self.eager_runs += 1
                return self.forward(left, right, init, iters, bf16)
            graph.left.copy_(left)
            graph.right.copy_(right)
            if graph.init is not None and init is not None:
                graph.init.copy_(init)
            graph.replay()
            self.replays += 1
            disparity, uncertainty = graph.outputs
            return disparity.clone(), uncertainty.clone()

    def clear(self) -> None:
        """Drop every graph (and its memory) and forget the keys seen."""
        with self._lock:
            self.graphs.clear()
            self.sightings.clear()
            self.uncapturable.clear()

    def _graph_for(self, key: GraphKey, left: Tensor, right: Tensor, init: Tensor | None) -> CapturedGraph | None:
        """The key's graph, captured now if this is its `capture_after`-th sighting; None: eager."""
        if key in self.graphs:
            self.graphs.move_to_end(key)
            return self.graphs[key]
        if key in self.uncapturable:
            return None
        seen = self.sightings.pop(key, 0) + 1
        if seen < self.capture_after:
            put_bounded(self.sightings, key, seen, 4 * self.max_graphs)
            return None
        static_left, static_right = left.clone(), right.clone()
        static_init = None if init is None else init.clone()

        def run() -> Maps:
            return self.forward(static_left, static_right, static_init, key.iters, key.bf16)

        try:
            replay, outputs = self.capture(run, left.device)
        except Exception as error:  # any capture failure falls back to eager runs
            warnings.warn(
                f"CUDA graph capture failed for {key}; running it eagerly: {error}", RuntimeWarning, stacklevel=3
            )
            put_bounded(self.uncapturable, key, None, 4 * self.max_graphs)
            return None
        self.captures += 1
        graph = CapturedGraph(static_left, static_right, static_init, replay, outputs)
        put_bounded(self.graphs, key, graph, self.max_graphs)
        return graph


def put_bounded(cache: OrderedDict[Key, Value], key: Key, value: Value, bound: int) -> None:
    """Insert `key` as the most recent entry of `cache`, dropping the oldest beyond `bound`."""
    cache[key] = value
    cache.move_to_end(key)
    while len(cache) > bound:
        cache.popitem(last=False)
