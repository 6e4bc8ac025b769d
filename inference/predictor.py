"""``StereoPredictor``: a network ready for inference, and its ``predict`` on images of any size.

What it puts together has a file each: the options (``inference.options``), the images in and the
maps out (``inference.prediction``), the padding (``inference.padding``), ``scale``
(``inference.scaling``), two passes and their auto rule (``inference.two_pass``), batches of mixed
sizes (``inference.batching``), the warm start of a video's frames (``inference.warm_start``), the
backends (``inference.torch_backend``, ``inference.cuda_graphs``, ``inference.openvino_backend``)
and the served uncertainty's calibration (``inference.uncertainty_calibration``); ``load_model``
(``inference.loading``) builds one.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from functools import partial
from pathlib import Path
from typing import Any, overload

import numpy as np
import torch
from torch import Tensor

from crestereo_pp.model.config import ModelConfig
from crestereo_pp.model.network import CREStereoPP, finest_stage_only
from crestereo_pp.model.upsample import resize_disparity
from crestereo_pp.model.weights import is_trained

from .backend_choice import Backend, Precision
from .batching import PaddedBatch, PairMaps, batch_groups
from .cuda_graphs import GraphedForward
from .flip import merge_flipped
from .forward import Forward, Maps
from .openvino_backend import MAX_COMPILED_BYTES, OpenVINOForward
from .options import InferenceOptions, Iterations, IterationsGiven, StageCounts, TwoPass
from .padding import Padding
from .prediction import Prediction, TensorPrediction, as_image_batch, image_size, same_colour
from .refinement import HostRefinement
from .row_alignment import RowOffset, align_rows
from .scaling import maps_at, resize_images, scaled_size
from .torch_backend import autocast_bf16
from .two_pass import PaddedForward, cold_maps, large_disparity_percentile
from .uncertainty_calibration import UncertaintyCalibration
from .warm_start import FrameStream


class StereoPredictor:
    """A network ready for inference (eval mode, on ``device``, no gradients).

    calibration: what the uncertainty map means for these weights
    (``inference.uncertainty_calibration``); when given, ``predict`` returns
    P(|error| > calibration.threshold_px) as the uncertainty, else the paper's raw U.
    training: the weights file's cumulative training record, as stored there ("total_steps",
    "total_pairs", "total_minutes", "runs" with each run's validation), or None.
    precision: "fp32", or "bf16" (see ``Precision``; the maps stay float32; bench/gpu_check
    and the model card measure how far they move); may be changed at any time.
    backend: as ``inference.backend_choice.resolve_backend`` picked it (``load_model``): "torch",
    or "openvino" to run every forward through ``openvino`` (an
    ``OpenVINOForward``: its graphs are cached under the weights' hash in ``cache_dir``, by
    default ``$CRESTEREO_CACHE_DIR`` or ``~/.cache/crestereo-pp``; calls whose graph is not in
    the cache run on torch, and only ``prepare`` exports one; the shapes it compiles are kept
    within ``compiled_bytes`` of their estimated memory, default MAX_COMPILED_BYTES).
    graphs: on a CUDA device with ``cuda_graphs``, the CUDA-graph replay
    (``inference.cuda_graphs``) that ``predict_pairs`` (so ``predict_batch``) runs its forward
    through, one graph per padded shape; else None.
    """

    def __init__(
        self,
        network: CREStereoPP,
        name: str,
        weights_sha256: str | None,
        device: str | torch.device,
        calibration: UncertaintyCalibration | None = None,
        training: dict[str, Any] | None = None,
        *,
        backend: Backend = "torch",
        precision: Precision = "fp32",
        cuda_graphs: bool = True,
        cache_dir: Path | None = None,
        compiled_bytes: int = MAX_COMPILED_BYTES,
    ) -> None:
        self.device = torch.device(device)
        self.network = network.to(self.device).eval()
        self.name = name
        self.weights_sha256 = weights_sha256
        self.calibration = calibration
        self.training = training
        self.backend: Backend = backend
        self.precision: Precision = precision
        self.graphs = GraphedForward(self.forward) if cuda_graphs and self.device.type == "cuda" else None
        self.openvino = (
            OpenVINOForward(
                self.network,
                self.forward,
                channels=self.config.feature_dim,
                cache_key=None if weights_sha256 is None else f"{name}-{weights_sha256[:16]}",
                cache_dir=cache_dir,
                max_bytes=compiled_bytes,
            )
            if self.backend == "openvino"
            else None
        )

    @property
    def config(self) -> ModelConfig:
        return self.network.config

    @property
    def trained(self) -> bool:
        """Whether the weights are trained (`model.weights.is_trained`); random ones never are."""
        return is_trained(self.training)

    @property
    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.network.parameters())

    def prepare(self, iters: Iterations = None, *, warm_start: bool = False, wait: bool = True) -> bool:
        """Make the fast path of this backend ready for these iterations (and a cold or warm
        start): on OpenVINO, read their graphs (``graph_iterations``) from the cache or export
        them (a minute or two each; side by side while the caller waits, or in the background,
        one at a time, where not ``wait``). Returns whether calls of that kind now run on this
        backend (always True on torch)."""
        if self.openvino is None:
            return True
        return self.openvino.prepare(self.graph_iterations(iters, warm_start), wait=wait)

    def ready(self, iters: Iterations = None, *, warm_start: bool = False) -> bool:
        """Whether calls with these iterations (and a cold or warm start) run on this predictor's
        backend now; False while OpenVINO is still exporting their graph (torch computes them)."""
        graphs = self.graph_iterations(iters, warm_start)
        return self.openvino is None or all(self.openvino.ready(counts) for counts in graphs)

    def graph_iterations(self, iters: Iterations, warm_start: bool) -> list[StageCounts]:
        """The stage counts of the forwards of a cold or a warm start with ``iters``, one graph
        each on OpenVINO (which takes a start disparity, zeros when cold): cold, every stage; warm,
        every stage (a video's next frame, ``FrameStream``) and 1/4 only (the second of two
        passes)."""
        counts = self.iterations(iters)
        return [counts, finest_stage_only(counts)] if warm_start else [counts]

    def iterations(self, iters: Iterations) -> StageCounts:
        """The counts per stage (1/16, 1/8, 1/4) that ``iters`` (already read, as
        ``InferenceOptions`` reads it) means for this model: None, the model's; one count, the
        finest stage's. The one place they are resolved; nothing here parses them again."""
        if iters is None:
            return self.config.iters
        if isinstance(iters, int):
            return (*self.config.iters[:2], iters)
        return iters

    @overload
    def predict(
        self,
        left: np.ndarray,
        right: np.ndarray | Tensor,
        *,
        iters: IterationsGiven = None,
        init_disparity: np.ndarray | Tensor | None = None,
        two_pass: TwoPass = "auto",
        scale: float = 1.0,
        raw_uncertainty: bool = False,
        flip: bool = False,
        blend_sgbm: bool = True,
        refine_edges: bool = True,
        align_rows: bool = True,
    ) -> Prediction: ...

    @overload
    def predict(
        self,
        left: Tensor,
        right: np.ndarray | Tensor,
        *,
        iters: IterationsGiven = None,
        init_disparity: np.ndarray | Tensor | None = None,
        two_pass: TwoPass = "auto",
        scale: float = 1.0,
        raw_uncertainty: bool = False,
        flip: bool = False,
        blend_sgbm: bool = True,
        refine_edges: bool = True,
        align_rows: bool = True,
    ) -> TensorPrediction: ...

    @torch.inference_mode()
    def predict(
        self,
        left: np.ndarray | Tensor,
        right: np.ndarray | Tensor,
        *,
        iters: IterationsGiven = None,
        init_disparity: np.ndarray | Tensor | None = None,
        two_pass: TwoPass = "auto",
        scale: float = 1.0,
        raw_uncertainty: bool = False,
        flip: bool = False,
        blend_sgbm: bool = True,
        refine_edges: bool = True,
        align_rows: bool = True,
    ) -> Prediction | TensorPrediction:
        """Disparity and uncertainty of a rectified pair of any size (see ``as_image_batch``).

        iters, two_pass, scale, raw_uncertainty, flip, blend_sgbm, refine_edges, align_rows: read
            once, here, as ``InferenceOptions`` (see there).
        init_disparity: warm start (e.g. the previous video frame's result), HxW array or
            (B, H, W) tensor, positive pixels: every stage runs (``iters``), the coarsest
            starting from it instead of from zero (see ``FrameStream``).
        two_pass: first a pass at half resolution, then refinement at full resolution from it
            (better for large disparities, coarser on fine detail): True, False, or "auto" (a quick
            quarter-resolution pass decides: two passes where it finds disparities above
            LARGE_DISPARITY_PX, one elsewhere, either way on the pair enlarged up to 1.5x as
            far as their range allows, or shrunk where two passes could not hold it, at scale 1;
            see ``two_pass.auto_way``). Ignored when
            init_disparity is given.
        scale: in (0, 1]: the network sees the pair resized by this factor (fewer pixels, so
            faster, and disparities shrunk by it); the maps come back at the input's size, the
            disparity in input pixels.
        raw_uncertainty: return the paper's U (in [0, 1], at most 0.5 after the first iteration)
            even when the weights carry a calibration; otherwise the uncertainty is the calibrated
            probability of an error above ``calibration.threshold_px`` where there is one.
        flip: also compute the pair upside down and merge the two answers (``inference.flip``):
            about twice the time, fewer large errors.
        blend_sgbm: average the answer with OpenCV's SGBM where the two agree within 4 px
            (``inference.sgbm``).
        refine_edges: refine the answer at its edges: its depth edges put where the left image's
            colour edges are (``inference.depth_edges``), the strip along the image's left edge
            whose matches fall outside the right image raised (``inference.border_strip``). With
            both False: the network's own answer.
        align_rows: where the right image's rows are off the left's by a quarter pixel or more,
            resample it onto them first (``inference.row_alignment``).
        A ``left`` array gives a ``Prediction`` (numpy arrays, copied from the device once); a
        ``left`` tensor a ``TensorPrediction`` (tensors on the predictor's device).
        """
        options = InferenceOptions(iters, two_pass, scale, raw_uncertainty, flip, blend_sgbm, refine_edges, align_rows)
        # arrays go as given (uploaded once, in predict_pairs; the refinement reads them on the host)
        lefts, rights = (pairs_of(image, self.device) for image in (left, right))
        inits = None
        if init_disparity is not None:  # (B, H, W) or H x W: one per pair of the batch
            init = torch.as_tensor(init_disparity, dtype=torch.float32, device=self.device)
            inits = one_per_pair(init.reshape(len(lefts), *image_size(left)))
        maps = self.predict_pairs(lefts, rights, options, inits, graphed=False)
        if isinstance(left, np.ndarray):
            return maps.on_host()[0]
        return maps.on_device()

    def predict_batch(
        self,
        lefts: Sequence[np.ndarray],
        rights: Sequence[np.ndarray],
        *,
        iters: IterationsGiven = None,
        two_pass: TwoPass = "auto",
        scale: float = 1.0,
        raw_uncertainty: bool = False,
        flip: bool = False,
        blend_sgbm: bool = True,
        refine_edges: bool = True,
        align_rows: bool = True,
        init_disparities: Sequence[np.ndarray] | None = None,
    ) -> list[Prediction]:
        """Several pairs (arrays, as ``predict`` takes them) in as few forward passes as their sizes
        allow (``batching.batch_groups``): ``predict_pairs`` with the options read once, here, as
        ``InferenceOptions``, its maps copied to the host."""
        options = InferenceOptions(iters, two_pass, scale, raw_uncertainty, flip, blend_sgbm, refine_edges, align_rows)
        return self.predict_pairs(lefts, rights, options, init_disparities).on_host()

    @torch.inference_mode()
    def predict_pairs(
        self,
        lefts: Sequence[np.ndarray | Tensor],
        rights: Sequence[np.ndarray | Tensor],
        options: InferenceOptions,
        init_disparities: Sequence[np.ndarray | Tensor] | None = None,
        *,
        graphed: bool = True,
    ) -> PairMaps:
        """The maps of several pairs with ``options`` (as they travel from a request: the
        service's batches), in as few forward passes as they allow, on the device
        (``PairMaps.on_host`` copies them to the host, once per batch that ran).
        Every call of the network with a request's options runs through here.

        lefts, rights: one image per pair, an array (as ``predict`` takes it) or a (1, 3|1, h, w)
        tensor. init_disparities: a warm start per pair (h x w px of its size), as ``predict``'s.
        graphed: on CUDA, replay the forward from a CUDA graph of the padded shape (``self.graphs``).
        Where ``options.align_rows``, each right array is first put onto its left image's rows
        (``inference.row_alignment``; tensors go as given): the network, SGBM and the
        refinements all see it so, and the result carries each pair's measured offset
        (``PairMaps.row_offsets``). A pair of arrays, one grey and one in colour, is computed in
        grey (``inference.prediction.same_colour``).

        Pairs of different sizes but one padded shape (a multiple of INPUT_MULTIPLE) run as one
        batch, each replicate-padded at the bottom and right to it exactly as a single pair is
        padded, so each result equals the pair computed alone up to float rounding; pairs of
        other padded shapes run as other batches (``inference.batching``). With
        ``two_pass=True`` or a ``scale`` the resized passes would see the padding: all pairs must
        then have one size; with ``two_pass="auto"`` (and no warm starts) pairs of different sizes
        run as one batch per size, unless none of them is large enough for two passes
        (``batch_groups``)."""
        sizes = [image_size(image) for image in lefts]
        if not lefts or len(lefts) != len(rights):
            raise ValueError(
                f"need as many right images as left ones (at least one), got {len(lefts)} and {len(rights)}"
            )
        right_sizes = [image_size(image) for image in rights]
        if right_sizes != sizes:
            raise ValueError(f"left and right differ in size: {sizes} vs {right_sizes}")
        if init_disparities is not None and len(init_disparities) != len(lefts):
            raise ValueError(f"need one warm start per pair, got {len(init_disparities)} for {len(lefts)}")
        pairs = [
            same_colour(left, right)
            if isinstance(left, np.ndarray) and isinstance(right, np.ndarray)
            else (left, right)  # tensors go as given
            for left, right in zip(lefts, rights, strict=True)
        ]
        lefts, rights = [left for left, _ in pairs], [right for _, right in pairs]
        row_offsets: list[RowOffset | None] = []
        if options.align_rows:  # arrays only: a device tensor stays where it is until the network
            aligned = [
                align_rows(left, right)
                if isinstance(left, np.ndarray) and isinstance(right, np.ndarray)
                else (right, None)
                for left, right in zip(lefts, rights, strict=True)
            ]
            rights, row_offsets = [right for right, _ in aligned], [offset for _, offset in aligned]
        iters = self.iterations(options.iters)
        forward = self.padded_forward(graphed)
        batches: list[tuple[list[int], PaddedBatch, Tensor, Tensor]] = []
        for group, two_pass in batch_groups(sizes, options.two_pass, init_disparities is not None, options.scale):
            batch = PaddedBatch.of([sizes[i] for i in group])
            left = batch.stack([as_image_batch(lefts[i], self.device) for i in group])
            right = batch.stack([as_image_batch(rights[i], self.device) for i in group])
            init = None
            if init_disparities is not None:
                init = batch.stack(
                    [
                        torch.as_tensor(init_disparities[i], dtype=torch.float32, device=self.device).reshape(
                            1, 1, *sizes[i]
                        )
                        for i in group
                    ]
                )
            disparity, uncertainty = self.batch_maps(batch, left, right, init, options, iters, two_pass, forward)
            if options.flip:
                turned = batch.upside_down
                maps = self.batch_maps(
                    batch,
                    turned(left),
                    turned(right),
                    None if init is None else turned(init),
                    options,
                    iters,
                    two_pass,
                    forward,
                )
                disparity, uncertainty = merge_flipped(disparity, uncertainty, *(turned(x) for x in maps))
            batches.append((group, batch, disparity[:, 0], uncertainty[:, 0]))
        return PairMaps.of(batches, HostRefinement.of((lefts, rights), options), row_offsets)

    def batch_maps(
        self,
        batch: PaddedBatch,
        left: Tensor,
        right: Tensor,
        init: Tensor | None,
        options: InferenceOptions,
        iters: StageCounts,
        two_pass: TwoPass,
        forward: PaddedForward,
    ) -> tuple[Tensor, Tensor]:
        """The maps of one batch of ``predict_pairs`` (as ``batch`` pads it: `left`, `right`
        (B, 3, H, W), `init` (B, 1, H, W) px or None for a cold start), computed once with
        `options` (their ``flip`` aside) and `two_pass`: disparity and uncertainty (served, or
        the paper's U with ``raw_uncertainty``), each (B, 1, H, W) at the batch's size."""
        height, width = left.shape[-2:]
        size = scaled_size(height, width, options.scale)
        scaled_left, scaled_right = left, right
        if size != (height, width):
            scaled_left, scaled_right = resize_images(left, size), resize_images(right, size)
        if init is None:
            maps = cold_maps(scaled_left, scaled_right, iters, two_pass, forward, resize=options.scale == 1.0)
        else:
            init = init if size == (height, width) else resize_disparity(init, *size)
            maps = forward(scaled_left, scaled_right, iters, init)
        disparity, uncertainty = maps_at(maps, height, width)
        if not options.raw_uncertainty:
            uncertainty = batch.served(uncertainty, disparity, left, right, self.served_uncertainty)
        return disparity, uncertainty

    def stream(self, options: InferenceOptions | None = None, warm_iters: IterationsGiven = None) -> FrameStream:
        """A video's pairs one at a time, each warm-started from the previous one (``FrameStream``)."""
        return FrameStream(self, options or InferenceOptions(), warm_iters)

    def predict_sequence(
        self,
        pairs: Iterable[tuple[np.ndarray, np.ndarray]],
        options: InferenceOptions | None = None,
        warm_iters: IterationsGiven = None,
    ) -> Iterator[Prediction]:
        """The maps of consecutive pairs of one camera (a video), lazily, in order: the first cold
        with ``options``, each next one warm-started from its predecessor's disparity with
        ``warm_iters`` (default: ``options.iters``; see ``FrameStream``);
        ``options`` default to the model's."""
        frames = self.stream(options, warm_iters)
        for left, right in pairs:
            yield frames.predict(left, right)

    @torch.inference_mode()
    def large_disparity_percentile(
        self, left: Tensor, right: Tensor, counts: StageCounts | None = None, forward: Forward | None = None
    ) -> Tensor:
        """(B,): the 99th percentile of each pair's disparity (px at H x W) in a quick pass at
        quarter resolution of the (B, 3, H, W) batch, what ``two_pass="auto"`` decides by.
        counts: the iterations (default the model's); forward: the backend, as ``forward_padded``'s
        (default this predictor's)."""
        return large_disparity_percentile(
            left,
            right,
            self.config.iters if counts is None else counts,
            self.padded_forward() if forward is None else partial(self.forward_padded, backend=forward),
        )

    def padded_forward(self, graphed: bool = False) -> PaddedForward:
        """``forward_padded`` with this predictor's backend bound (the ``PaddedForward`` that
        ``two_pass`` computes through): OpenVINO where it runs, else torch, replayed from CUDA
        graphs where `graphed` and the predictor has them."""
        return partial(self.forward_padded, backend=self.openvino or (self.graphs if graphed else None))

    def served_uncertainty(self, raw: Tensor, disparity: Tensor, left: Tensor, right: Tensor) -> Tensor:
        """The uncertainty as served, (B, 1, H, W), from the paper's U `raw` (B, 1, H, W), the
        `disparity` (B, 1, H, W) and the `left` and `right` images (B, 3, H, W) it answers:
        P(|error| > threshold_px) through the weights' calibration where they carry one, else U
        itself."""
        return raw if self.calibration is None else self.calibration.apply(raw, disparity, left, right)

    def forward_padded(
        self,
        left: Tensor,
        right: Tensor,
        iters: StageCounts,
        init: Tensor | None,
        backend: Forward | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Pad (B,3,H,W) inputs to multiples of 32, run `backend` (``self.graphs`` or
        ``self.openvino``; default ``self.forward``, torch eager), crop back. Returns disparity
        (clipped at 0) and uncertainty, each (B, 1, H, W). With its backend bound, the
        ``PaddedForward`` the two-pass rule calls (``padded_forward``)."""
        padding = Padding.to_multiple(*left.shape[-2:])
        disparity, uncertainty = (backend or self.forward)(
            padding.pad(left),
            padding.pad(right),
            None if init is None else padding.pad(init),
            iters,
            self.precision == "bf16",
        )
        return padding.crop(disparity).clamp(min=0.0), padding.crop(uncertainty)

    def forward(self, left: Tensor, right: Tensor, init: Tensor | None, iters: StageCounts, bf16: bool) -> Maps:
        """The torch backend: the network, eagerly, on padded (B, 3, H, W) images in [0, 255]
        (H, W multiples of 32) and an optional (B, 1, H, W) warm start (px), under bf16 autocast
        when `bf16` (``inference.torch_backend``): disparity and uncertainty, float32
        (B, 1, H, W). The function ``self.graphs`` captures and ``self.openvino`` falls back to."""
        with autocast_bf16(self.device, bf16, cache=False):
            out = self.network(left, right, iters=iters, init_disparity=init)
        return out.disparity.float(), out.uncertainty.float()


def one_per_pair(batch: Tensor) -> list[Tensor]:
    """A (B, ...) batch as B tensors (1, ...), views of it: one per pair, as ``predict_pairs`` takes them."""
    return [batch[i : i + 1] for i in range(batch.shape[0])]


def pairs_of(image: np.ndarray | Tensor, device: torch.device) -> list[np.ndarray] | list[Tensor]:
    """``predict``'s image as ``predict_pairs`` takes it: an array as it is (one pair), a
    (B, 3|1, H, W) tensor as B tensors (1, 3, H, W) on `device`."""
    return [image] if isinstance(image, np.ndarray) else one_per_pair(as_image_batch(image, device))
