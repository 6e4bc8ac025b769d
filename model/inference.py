"""Inference API: ``load_model`` and ``StereoPredictor.predict`` on images of any size."""

from __future__ import annotations

import contextlib
import os
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, NamedTuple, TypeVar, overload

import numpy as np
import torch
from torch import Tensor
from torch.nn import functional as F

from .calibration import UncertaintyCalibration
from .config import ModelConfig
from .cuda_graphs import Forward, GraphedForward
from .network import CREStereoPP, finest_stage_only, padded_size
from .openvino_backend import OpenVINOForward, native_bf16, openvino_available
from .options import InferenceOptions, Iterations, StageCounts, TwoPass, WarmStart, parse_iterations
from .upsample import resize_disparity
from .weights import USABLE_BAD2, WEIGHTS_DIR, file_sha256, is_trained, network_from_weights, read_weights

Precision = Literal["fp32", "bf16"]
"""fp32: the network in float32; bf16: torch under bf16 autocast, OpenVINO with bf16 inference
precision; the maps stay float32 either way."""

Backend = Literal["torch", "openvino"]
"""torch: eager (CUDA graphs on a GPU), the reference; openvino: compiled for the CPU
(``model.openvino_backend``)."""

BackendChoice = Literal["auto", "torch", "openvino"]
PrecisionChoice = Literal["auto", "fp32", "bf16"]


def resolve_backend(backend: BackendChoice, device: torch.device) -> Backend:
    """``auto``: ``$CRESTEREO_BACKEND`` where set, else OpenVINO on a CPU where it is installed,
    else torch. ValueError where OpenVINO is asked for and cannot run (another device, or not
    installed), or for an unknown name."""
    if backend == "auto":
        backend = os.environ.get("CRESTEREO_BACKEND", "auto").strip().lower() or "auto"  # type: ignore[assignment]
        if backend == "auto":
            return "openvino" if device.type == "cpu" and openvino_available() else "torch"
    if backend not in ("torch", "openvino"):
        raise ValueError(f"unknown backend {backend!r}; choose auto, torch or openvino")
    if backend == "openvino":
        if device.type != "cpu":
            raise ValueError(f"the openvino backend runs on the CPU, not on {device}")
        if not openvino_available():
            raise ValueError("the openvino backend needs the openvino package: pip install openvino")
    return backend


def resolve_precision(precision: PrecisionChoice, backend: Backend) -> Precision:
    """``auto``: bf16 for OpenVINO on a CPU that computes bf16 natively (AMX, AVX512-BF16),
    fp32 everywhere else (torch's bf16 autocast on a CPU spends its time casting)."""
    if precision == "auto":
        return "bf16" if backend == "openvino" and native_bf16() else "fp32"
    return precision


LARGE_DISPARITY_PX = 90.0
"""``two_pass="auto"`` computes a pair in two passes where the 99th percentile of its quick
quarter-resolution pass's disparity (``StereoPredictor.large_disparity_percentile``) is above this
(px of the image the network sees). The single pass of lite's weights misses disparities beyond
about 90-100 px on real pairs (on procedural ones beyond about 130), where starting from a
half-resolution pass finds them; below, the single pass keeps finer detail. Measured on the dev
pairs with ``python -m crestereo_pp.evaluation.two_pass_rule``."""

QUICK_PASS_MIN_SIDE = 48
"""``two_pass="auto"``'s quick pass at quarter resolution needs at least this many pixels per side
to measure anything: on 16 x 24 or 32 x 48 px it reads 99th-percentile disparities of 140-220 px
on pairs whose true disparity is 4-16 px (and would send them to two passes)."""

MIN_SCALED_SIDE = 16
"""With ``scale``, the pair the network sees keeps at least this many pixels per side: below it
the network sees too little to match, and its disparities, multiplied by 1 / scale, come out
wider than the image."""


def scaled_size(height: int, width: int, scale: float) -> tuple[int, int]:
    """(height, width) of a ``height`` x ``width`` pair resized by ``scale`` in (0, 1], as
    ``predict(..., scale=...)`` runs it; ValueError where a side would fall below MIN_SCALED_SIDE
    (an image already smaller than that must come at scale 1)."""
    if not 0.0 < scale <= 1.0:
        raise ValueError(f"scale must be in (0, 1], got {scale}")
    size = (round(height * scale), round(width * scale))
    if scale < 1.0 and min(size) < MIN_SCALED_SIDE:
        raise ValueError(
            f"scale {scale:g} would run the {width}x{height} pair at {size[1]}x{size[0]}; "
            f"each side must stay at least {MIN_SCALED_SIDE} px (use a larger scale)"
        )
    return size


class Prediction(NamedTuple):
    """Disparity (positive, pixels of the left image) and uncertainty (in [0, 1]) maps of a pair
    given as arrays (``predict``, ``predict_batch``): float32 numpy HxW, on the host."""

    disparity: np.ndarray
    uncertainty: np.ndarray


class TensorPrediction(NamedTuple):
    """The maps of ``Prediction`` for pairs given as tensors (``predict``): float32 torch
    (B, H, W) on the predictor's device."""

    disparity: Tensor
    uncertainty: Tensor


def load_model(
    name: str = "lite",
    weights: str | Path | None = None,
    device: str | torch.device = "cpu",
    *,
    backend: BackendChoice = "auto",
    precision: PrecisionChoice = "auto",
    cuda_graphs: bool = True,
    cache_dir: str | Path | None = None,
    prepare_iters: Sequence[Iterations] = (),
) -> StereoPredictor:
    """Build the ``name`` network (``lite`` | ``full``) and load its weights.

    ``weights``: a weights file or training checkpoint (a dict with ``"model"`` = state_dict and
    ``"config"``); None loads the bundled ``model/weights/{name}.pt`` if present, else the network is
    randomly initialised (seed 0, so every process gets the same one) with a warning.
    ``backend`` and ``precision``: see ``resolve_backend`` and ``resolve_precision``; the
    predictor's ``backend`` and ``precision`` say what was picked. ``cuda_graphs`` and
    ``cache_dir``: see ``StereoPredictor``. ``prepare_iters``: iteration settings whose fast
    paths, for cold and warm starts, are made ready in the background at once (``prepare`` with
    ``wait=False``: OpenVINO reads their graphs from the cache or exports them).
    """
    device = torch.device(device)
    chosen = resolve_backend(backend, device)
    options: dict[str, Any] = {
        "backend": chosen,
        "precision": resolve_precision(precision, chosen),
        "cuda_graphs": cuda_graphs,
        "cache_dir": None if cache_dir is None else Path(cache_dir),
    }
    path = Path(weights) if weights is not None else WEIGHTS_DIR / f"{name}.pt"
    if weights is None and not path.is_file():
        warnings.warn(
            f"no weights at {path}: the {name!r} model is randomly initialised and its predictions are meaningless",
            RuntimeWarning,
            stacklevel=2,
        )
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)
            network = CREStereoPP(ModelConfig.preset(name))
        predictor = StereoPredictor(network, name, None, device, **options)
    else:
        payload = read_weights(path)
        if not is_trained(payload.get("training")):
            warnings.warn(
                f"the {name!r} weights at {path} are untrained (no validation on real pairs reaching "
                f"{USABLE_BAD2:g} % bad-2): their maps are not usable",
                RuntimeWarning,
                stacklevel=2,
            )
        calibration = payload.get("calibration")
        predictor = StereoPredictor(
            network_from_weights(payload, name),
            name,
            file_sha256(path),
            device,
            UncertaintyCalibration.from_dict(calibration) if calibration is not None else None,
            payload.get("training"),
            **options,
        )
    for iters in prepare_iters:
        for warm_start in (False, True):
            predictor.prepare(iters, warm_start=warm_start, wait=False)
    return predictor


def two_pass_possible(height: int, width: int) -> bool:
    """Whether ``two_pass="auto"`` considers two passes for a pair of this size (as the network
    sees it): where its quick pass at quarter resolution keeps at least QUICK_PASS_MIN_SIDE px per
    side (192 px and more); smaller pairs take one pass."""
    return min(height, width) // 4 >= QUICK_PASS_MIN_SIDE


def as_image_batch(image: np.ndarray | Tensor, device: torch.device) -> Tensor:
    """An image as (B, 3, H, W) float32 in [0, 255] on ``device``.

    Arrays: HxWx3 RGB, HxWx4 (alpha dropped), HxW or HxWx1 grayscale (replicated to RGB);
    uint8 as is, uint16 scaled to [0, 255], floats taken as [0, 255]. Tensors: (B, 3|1, H, W).
    """
    if isinstance(image, np.ndarray):
        array = image[..., None] if image.ndim == 2 else image
        if array.ndim != 3 or array.shape[2] not in (1, 3, 4):
            raise ValueError(f"expected an HxW, HxWx1, HxWx3 or HxWx4 image, got shape {image.shape}")
        scale = 255.0 / 65535.0 if array.dtype == np.uint16 else 1.0
        # writable: torch warns about every read-only array (decoded from bytes, memory-mapped)
        pixels = np.require(array[..., :3], requirements=("C", "W"))
        batch = torch.from_numpy(pixels).to(device).permute(2, 0, 1)[None]
        batch = batch.float() * scale
    elif isinstance(image, Tensor):
        if image.ndim != 4 or image.shape[1] not in (1, 3):
            raise ValueError(f"expected a (B, 3, H, W) or (B, 1, H, W) tensor, got {tuple(image.shape)}")
        batch = image.to(device=device, dtype=torch.float32)
    else:
        raise TypeError(f"expected a numpy array or a torch tensor, got {type(image).__name__}")
    return batch.expand(-1, 3, -1, -1) if batch.shape[1] == 1 else batch


def shrink(images: Tensor, size: tuple[int, int]) -> Tensor:
    """(B, 3, H, W) images resized down to ``size`` = (height, width), antialiased."""
    return F.interpolate(images, size=size, mode="bilinear", antialias=True, align_corners=False)


def half_resolution_start(left: Tensor, right: Tensor, coarse: Callable[[Tensor, Tensor], Tensor]) -> Tensor:
    """The first of two passes: the (B, 1, H, W) disparity (px at H x W, positive) that
    ``coarse`` finds on the (B, 3, H, W) pair shrunk to half its size, resized back to H x W. The
    second pass refines it at full resolution (``init_disparity``), at inference with
    ``two_pass`` and in training with ``TrainConfig.two_pass_fraction``."""
    height, width = left.shape[-2:]
    half_size = (max(1, height // 2), max(1, width // 2))
    return resize_disparity(coarse(shrink(left, half_size), shrink(right, half_size)), height, width)


T = TypeVar("T", Tensor, np.ndarray)


@dataclass(frozen=True)
class Padding:
    """Replicate padding of an image of (height, width) px on the bottom and right to
    (padded_height, padded_width), and the crop that takes a map of the padded image back."""

    height: int
    width: int
    padded_height: int
    padded_width: int

    @staticmethod
    def to_multiple(height: int, width: int) -> Padding:
        """The padding the network needs: to multiples of INPUT_MULTIPLE."""
        return Padding(height, width, padded_size(height), padded_size(width))

    def pad(self, x: Tensor) -> Tensor:
        """(B, C, height, width) -> (B, C, padded_height, padded_width), edges replicated."""
        if (self.padded_height, self.padded_width) == tuple(x.shape[-2:]):
            return x
        return F.pad(x, (0, self.padded_width - x.shape[-1], 0, self.padded_height - x.shape[-2]), mode="replicate")

    def crop(self, x: T) -> T:
        """A map of the padded image (..., padded_height, padded_width), tensor or array, cut back
        to (..., height, width)."""
        return x[..., : self.height, : self.width]


def to_host(disparity: Tensor, uncertainty: Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Two maps of one shape (float32 tensors on any device) as numpy arrays, in one copy to the
    host: the only device-to-host transfer of a prediction."""
    both = torch.stack((disparity, uncertainty)).cpu().numpy()
    return both[0], both[1]


def autocast_bf16(device: torch.device, enabled: bool, *, cache: bool = True) -> contextlib.AbstractContextManager[Any]:
    """bf16 autocast on `device` when `enabled`, else nothing (so that any device, "meta"
    included, runs in float32). cache: reuse each weight's bf16 copy within the context (off
    for a forward that a CUDA graph captures, as the PyTorch CUDA-graph notes ask)."""
    if not enabled:
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=torch.bfloat16, cache_enabled=cache)


class StereoPredictor:
    """A network ready for inference (eval mode, on ``device``, no gradients).

    calibration: what the uncertainty map means for these weights (``model.calibration``); when
    given, ``predict`` returns P(|error| > calibration.threshold_px) as the uncertainty, else the
    paper's raw U. training: the weights file's cumulative training record, as stored there
    ("total_steps", "total_pairs", "total_minutes", "runs" with each run's validation), or None.
    precision: "fp32", or "bf16" (see ``Precision``; the maps stay float32; bench/gpu_check.py
    and the model card measure how far they move); may be changed at any time.
    backend: "torch", or "openvino" to run every forward through ``openvino`` (an
    ``OpenVINOForward``: its graphs are cached under the weights' hash in ``cache_dir``, by
    default ``$CRESTEREO_CACHE_DIR`` or ``~/.cache/crestereo-pp``; calls whose graph is not in
    the cache run on torch, and only ``prepare`` exports one).
    graphs: on a CUDA device with ``cuda_graphs``, the CUDA-graph replay (``model.cuda_graphs``)
    that ``predict_batch`` runs its forward through, one graph per padded shape; else None.
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
    ) -> None:
        self.device = torch.device(device)
        self.network = network.to(self.device).eval()
        self.name = name
        self.weights_sha256 = weights_sha256
        self.calibration = calibration
        self.training = training
        self.backend: Backend = resolve_backend(backend, self.device)
        self.precision: Precision = precision
        self.graphs = GraphedForward(self.forward) if cuda_graphs and self.device.type == "cuda" else None
        self.openvino = (
            OpenVINOForward(
                self.network,
                self.forward,
                cache_key=None if weights_sha256 is None else f"{name}-{weights_sha256[:16]}-torch{torch.__version__}",
                cache_dir=cache_dir,
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
        start): on OpenVINO, read its graphs (``graph_kinds``) from the cache or export them
        (minutes each; in the background unless ``wait``). Returns whether calls of that kind now
        run on this backend (always True on torch)."""
        if self.openvino is None:
            return True
        kinds = self.graph_kinds(iters, warm_start)  # a list below: every export starts, even after one not ready
        return all([self.openvino.prepare(counts, init, wait=wait) for counts, init in kinds])

    def ready(self, iters: Iterations = None, *, warm_start: bool = False) -> bool:
        """Whether calls with these iterations (and a cold or warm start) run on this predictor's
        backend now; False while OpenVINO is still exporting their graph (torch computes them)."""
        kinds = self.graph_kinds(iters, warm_start)
        return self.openvino is None or all(self.openvino.ready(counts, init) for counts, init in kinds)

    def graph_kinds(self, iters: Iterations, warm_start: bool) -> list[tuple[StageCounts, bool]]:
        """The forwards (stage counts, whether they take a start disparity) of a cold or a warm
        start with ``iters``: cold, one from zero; warm, the two that start from a given
        disparity, every stage (a video's next frame, ``FrameStream``) and 1/4 only (the second
        of two passes)."""
        counts = self.iterations(iters)
        return [(counts, True), (finest_stage_only(counts), True)] if warm_start else [(counts, False)]

    def iterations(self, iters: Iterations) -> StageCounts:
        """The counts per stage (1/16, 1/8, 1/4) that ``iters`` (see ``parse_iterations``) means here."""
        parsed = parse_iterations(iters)
        if parsed is None:
            return self.config.iters
        if isinstance(parsed, int):
            return (*self.config.iters[:2], parsed)
        return parsed

    @overload
    def predict(
        self,
        left: np.ndarray,
        right: np.ndarray | Tensor,
        *,
        iters: Iterations = None,
        init_disparity: np.ndarray | Tensor | None = None,
        two_pass: TwoPass = "auto",
        scale: float = 1.0,
        raw_uncertainty: bool = False,
    ) -> Prediction: ...

    @overload
    def predict(
        self,
        left: Tensor,
        right: np.ndarray | Tensor,
        *,
        iters: Iterations = None,
        init_disparity: np.ndarray | Tensor | None = None,
        two_pass: TwoPass = "auto",
        scale: float = 1.0,
        raw_uncertainty: bool = False,
    ) -> TensorPrediction: ...

    @torch.inference_mode()
    def predict(
        self,
        left: np.ndarray | Tensor,
        right: np.ndarray | Tensor,
        *,
        iters: Iterations = None,
        init_disparity: np.ndarray | Tensor | None = None,
        two_pass: TwoPass = "auto",
        scale: float = 1.0,
        raw_uncertainty: bool = False,
    ) -> Prediction | TensorPrediction:
        """Disparity and uncertainty of a rectified pair of any size (see ``as_image_batch``).

        init_disparity: warm start (e.g. the previous video frame's result), HxW array or
            (B, H, W) tensor, positive pixels: every stage runs (``iters``), the coarsest
            starting from it instead of from zero (see ``FrameStream``).
        two_pass: first a pass at half resolution, then refinement at full resolution from it
            (better for large disparities, coarser on fine detail): True, False, or "auto" (two
            passes where a quick quarter-resolution pass finds disparities above
            LARGE_DISPARITY_PX). Ignored when init_disparity is given.
        scale: in (0, 1]: the network sees the pair resized by this factor (fewer pixels, so
            faster, and disparities shrunk by it); the maps come back at the input's size, the
            disparity in input pixels.
        raw_uncertainty: return the paper's U (in [0, 1], at most 0.5 after the first iteration)
            even when the weights carry a calibration; otherwise the uncertainty is the calibrated
            probability of an error above ``calibration.threshold_px`` where there is one.
        A ``left`` array gives a ``Prediction`` (numpy arrays, copied from the device once); a
        ``left`` tensor a ``TensorPrediction`` (tensors on the predictor's device).
        """
        disparity, uncertainty = self.predict_tensors(
            as_image_batch(left, self.device),
            as_image_batch(right, self.device),
            iters=iters,
            init_disparity=init_disparity,
            two_pass=two_pass,
            scale=scale,
            raw_uncertainty=raw_uncertainty,
            graphed=False,
        )
        if isinstance(left, np.ndarray):
            return Prediction(*to_host(disparity[0], uncertainty[0]))
        return TensorPrediction(disparity, uncertainty)

    @torch.inference_mode()
    def predict_batch(
        self,
        lefts: Sequence[np.ndarray],
        rights: Sequence[np.ndarray],
        *,
        iters: Iterations = None,
        two_pass: TwoPass = "auto",
        scale: float = 1.0,
        raw_uncertainty: bool = False,
        init_disparities: Sequence[np.ndarray] | None = None,
    ) -> list[Prediction]:
        """Several pairs (arrays, as ``predict`` takes them) in one forward pass; the maps come
        back as numpy HxW arrays, copied from the device once for the whole batch. On CUDA the
        forward is replayed from a CUDA graph of the padded shape (``self.graphs``).
        ``init_disparities``: a warm start per pair (HxW px of its size), as ``predict``'s.

        Pairs of different sizes are replicate-padded at the bottom and right to one shape, a
        multiple of INPUT_MULTIPLE, exactly as ``predict`` pads a single pair, so each result
        equals ``predict`` on its pair alone up to float rounding. With ``two_pass=True`` or a
        ``scale`` the resized passes would see the padding: all pairs must then have one size;
        with ``two_pass="auto"`` (and no warm starts) pairs of different sizes run as one batch per size,
        unless none of them is large enough for two passes (``two_pass_possible``).
        """
        if not lefts or len(lefts) != len(rights):
            raise ValueError(
                f"need as many right images as left ones (at least one), got {len(lefts)} and {len(rights)}"
            )
        sizes = [image.shape[:2] for image in lefts]
        auto_mixed = len(set(sizes)) > 1 and two_pass == "auto" and init_disparities is None and scale == 1.0
        if auto_mixed and not any(two_pass_possible(*size) for size in sizes):
            two_pass = False  # none is large enough for two passes: one padded batch
        elif auto_mixed:
            results: dict[int, Prediction] = {}
            for size in dict.fromkeys(sizes):
                group = [i for i, other in enumerate(sizes) if other == size]
                predictions = self.predict_batch(
                    [lefts[i] for i in group],
                    [rights[i] for i in group],
                    iters=iters,
                    two_pass=two_pass,
                    raw_uncertainty=raw_uncertainty,
                )
                results.update(zip(group, predictions, strict=True))
            return [results[i] for i in range(len(lefts))]
        if len(set(sizes)) > 1 and (two_pass is True or scale != 1.0):
            raise ValueError("pairs of different sizes can only be batched without two_pass or scale")
        height = max(h for h, _ in sizes)
        width = max(w for _, w in sizes)
        if len(set(sizes)) > 1:
            height, width = padded_size(height), padded_size(width)

        paddings = [Padding(h, w, height, width) for h, w in sizes]

        def stack(images: Sequence[Tensor]) -> Tensor:
            return torch.cat([padding.pad(image) for padding, image in zip(paddings, images, strict=True)])

        init: Tensor | None = None
        if init_disparities is not None:
            if len(init_disparities) != len(lefts):
                raise ValueError(f"need one warm start per pair, got {len(init_disparities)} for {len(lefts)}")
            init = stack(
                [torch.as_tensor(d, dtype=torch.float32, device=self.device)[None, None] for d in init_disparities]
            )[:, 0]

        padded = len(set(sizes)) > 1
        left_batch = stack([as_image_batch(image, self.device) for image in lefts])
        disparity_batch, uncertainty_batch = self.predict_tensors(
            left_batch,
            stack([as_image_batch(image, self.device) for image in rights]),
            iters=iters,
            init_disparity=init,
            two_pass=two_pass,
            scale=scale,
            raw_uncertainty=raw_uncertainty or padded,
            graphed=True,
        )
        if padded and not raw_uncertainty:  # served from each pair's own maps, borders as ``predict`` sees them
            uncertainty_batch = uncertainty_batch.clone()
            for i, padding in enumerate(paddings):
                maps = (uncertainty_batch[:, None], disparity_batch[:, None], left_batch)
                pair_raw, pair_disparity, pair_left = (padding.crop(x[i : i + 1]) for x in maps)
                served = self.served_uncertainty(pair_raw, pair_disparity, pair_left)
                uncertainty_batch[i, : padding.height, : padding.width] = served[0, 0]
        disparity, uncertainty = to_host(disparity_batch, uncertainty_batch)
        return [
            Prediction(
                np.ascontiguousarray(padding.crop(disparity[i])), np.ascontiguousarray(padding.crop(uncertainty[i]))
            )
            for i, padding in enumerate(paddings)
        ]

    def stream(self, options: InferenceOptions | None = None, warm_iters: Iterations = None) -> FrameStream:
        """A video's pairs one at a time, each warm-started from the previous one (``FrameStream``)."""
        return FrameStream(self, options or InferenceOptions(), warm_iters)

    def predict_sequence(
        self,
        pairs: Iterable[tuple[np.ndarray, np.ndarray]],
        options: InferenceOptions | None = None,
        warm_iters: Iterations = None,
    ) -> Iterator[Prediction]:
        """The maps of consecutive pairs of one camera (a video), lazily, in order: the first cold
        with ``options``, each next one warm-started from its predecessor's disparity with
        ``warm_iters`` (default: ``options.iters``; see ``FrameStream``);
        ``options`` default to the model's."""
        frames = self.stream(options, warm_iters)
        for left, right in pairs:
            yield frames.predict(left, right)

    def predict_tensors(
        self,
        left_batch: Tensor,
        right_batch: Tensor,
        *,
        iters: Iterations,
        init_disparity: np.ndarray | Tensor | None,
        two_pass: TwoPass,
        scale: float,
        raw_uncertainty: bool,
        graphed: bool,
    ) -> tuple[Tensor, Tensor]:
        """``predict`` on (B, 3, H, W) float images on the device: disparity and uncertainty,
        float32 (B, H, W) on the device. graphed: run the forward through ``self.graphs``
        (where there are graphs)."""
        if left_batch.shape != right_batch.shape:
            raise ValueError(f"left and right differ in size: {tuple(left_batch.shape)} vs {tuple(right_batch.shape)}")
        forward = self.openvino or (self.graphs if graphed and self.graphs is not None else self.forward)
        counts = self.iterations(iters)
        height, width = left_batch.shape[-2:]
        size = scaled_size(height, width, scale)
        original_left = left_batch
        if size != (height, width):
            left_batch, right_batch = (shrink(image, size) for image in (left_batch, right_batch))
        if init_disparity is not None:
            init = torch.as_tensor(init_disparity, dtype=torch.float32, device=self.device)
            init = init.reshape(left_batch.shape[0], 1, height, width)
            init = init if size == (height, width) else resize_disparity(init, *size)
            disparity, uncertainty = self.forward_padded(left_batch, right_batch, counts, init, forward)
        else:
            disparity, uncertainty = self.forward_cold(left_batch, right_batch, counts, two_pass, forward)
        if size != (height, width):
            disparity = resize_disparity(disparity, height, width)
            uncertainty = F.interpolate(uncertainty, size=(height, width), mode="bilinear", align_corners=False)
        if not raw_uncertainty:
            uncertainty = self.served_uncertainty(uncertainty, disparity, original_left)
        return disparity[:, 0], uncertainty[:, 0]

    def forward_cold(
        self, left: Tensor, right: Tensor, counts: StageCounts, two_pass: TwoPass, forward: Forward
    ) -> tuple[Tensor, Tensor]:
        """The maps of (B, 3, H, W) pairs without a warm start, each (B, 1, H, W): one pass, two
        passes (the second refining at 1/4 only from a half-resolution one), or, with "auto", two
        passes for the pairs whose ``large_disparity_percentile`` is above LARGE_DISPARITY_PX and one
        for the others (one for all where ``two_pass_possible`` says the pairs are too small)."""
        if two_pass == "auto" and not two_pass_possible(*left.shape[-2:]):
            return self.forward_cold(left, right, counts, False, forward)
        if two_pass == "auto":
            needs = self.large_disparity_percentile(left, right, counts, forward) > LARGE_DISPARITY_PX
            if bool(needs.all()) or not bool(needs.any()):
                return self.forward_cold(left, right, counts, bool(needs.all()), forward)
            disparity, uncertainty = torch.empty_like(left[:, :1]), torch.empty_like(left[:, :1])
            for group, two in ((needs, True), (~needs, False)):
                disparity[group], uncertainty[group] = self.forward_cold(
                    left[group], right[group], counts, two, forward
                )
            return disparity, uncertainty
        if not two_pass:
            return self.forward_padded(left, right, counts, None, forward)
        init = half_resolution_start(
            left,
            right,
            lambda small_left, small_right: self.forward_padded(small_left, small_right, counts, None, forward)[0],
        )
        return self.forward_padded(left, right, finest_stage_only(counts), init, forward)

    @torch.inference_mode()
    def large_disparity_percentile(
        self, left: Tensor, right: Tensor, counts: StageCounts | None = None, forward: Forward | None = None
    ) -> Tensor:
        """(B,): the 99th percentile of each pair's disparity (px at H x W) in a quick pass at
        quarter resolution of the (B, 3, H, W) batch, what ``two_pass="auto"`` decides by.
        counts: the iterations (default the model's); forward: as ``forward_padded``'s
        (default this predictor's backend)."""
        height, width = left.shape[-2:]
        quarter = (max(1, height // 4), max(1, width // 4))
        coarse, _ = self.forward_padded(
            shrink(left, quarter),
            shrink(right, quarter),
            self.config.iters if counts is None else counts,
            None,
            forward or self.openvino,
        )
        return torch.quantile(coarse.flatten(1), 0.99, dim=1) * (width / quarter[1])

    def served_uncertainty(self, raw: Tensor, disparity: Tensor, left: Tensor) -> Tensor:
        """The uncertainty as served, (B, 1, H, W), from the paper's U `raw` (B, 1, H, W), the
        `disparity` (B, 1, H, W) and the `left` image (B, 3, H, W) it answers: P(|error| >
        threshold_px) through the weights' calibration where they carry one, else U itself."""
        return raw if self.calibration is None else self.calibration.apply(raw, disparity, left)

    def forward_padded(
        self,
        left: Tensor,
        right: Tensor,
        iters: StageCounts,
        init: Tensor | None,
        forward: Forward | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Pad (B,3,H,W) inputs to multiples of 32, run `forward` (default ``self.forward``),
        crop back. Returns disparity (clipped at 0) and uncertainty, each (B, 1, H, W)."""
        padding = Padding.to_multiple(*left.shape[-2:])
        disparity, uncertainty = (forward or self.forward)(
            padding.pad(left),
            padding.pad(right),
            None if init is None else padding.pad(init),
            iters,
            self.precision == "bf16",
        )
        return padding.crop(disparity).clamp(min=0.0), padding.crop(uncertainty)

    def forward(
        self, left: Tensor, right: Tensor, init: Tensor | None, iters: StageCounts, bf16: bool
    ) -> tuple[Tensor, Tensor]:
        """The network, eagerly, on padded (B, 3, H, W) images in [0, 255] (H, W multiples of 32)
        and an optional (B, 1, H, W) warm start (px), under bf16 autocast when `bf16`: disparity
        and uncertainty, float32 (B, 1, H, W). The function ``self.graphs`` captures."""
        with autocast_bf16(self.device, bf16, cache=False):
            out = self.network(left, right, iters=iters, init_disparity=init)
        return out.disparity.float(), out.uncertainty.float()


class FrameStream:
    """Consecutive pairs of one camera computed one at a time, each warm-started from its
    predecessor (the rules, and why every stage runs, are ``WarmStart``'s)."""

    def __init__(self, predictor: StereoPredictor, options: InferenceOptions, warm_iters: Iterations = None) -> None:
        self.predictor = predictor
        self.warm_start = WarmStart(options, warm_iters)

    def predict(self, left: np.ndarray, right: np.ndarray) -> Prediction:
        """The maps of the next pair (arrays, as ``StereoPredictor.predict`` takes them)."""
        options, init = self.warm_start.next(*left.shape[:2])
        prediction = self.predictor.predict(left, right, init_disparity=init, **options.keywords())
        self.warm_start.record(prediction.disparity)
        return prediction

    def restart(self) -> None:
        """Forget the previous frame (a cut): the next pair is computed cold."""
        self.warm_start.restart()
