"""The bodies of the answers of `POST /disparity` and `/disparity/stream`, one per response format."""

from __future__ import annotations

import base64
import io
import json

import numpy as np

from crestereo_pp.inference import RowOffset
from crestereo_pp.service.api.schemas import (
    AnswerFacts,
    DisparityOptions,
    DisparityResponse,
    EncodedArray,
    Frame,
    ImageSize,
    OutputFormat,
    RectifiedCamera,
    RowOffsetReport,
    Timings,
)
from crestereo_pp.service.batching.batcher import JobResult
from crestereo_pp.service.batching.stereo import StereoMaps
from crestereo_pp.service.uploads.images import ImageHeader
from crestereo_pp.stereo_data.formats import KITTI_SCALE, UNCERTAINTY_SCALE, encode_png, encode_png16, png_with_text
from crestereo_pp.stereo_data.output_maps import OutputOptions, PredictionOutputs
from crestereo_pp.stereo_data.pointcloud import DepthRange
from crestereo_pp.stereo_data.rig import Rectifier
from crestereo_pp.stereo_data.visualize import preview

FACTS = "facts"
"""The name the facts go by inside a binary answer: its npz array, PNG tEXt keyword and PLY comment."""


def facts_text(facts: AnswerFacts) -> str:
    """`facts` as one line of ASCII JSON (as in a `format=json` body)."""
    return json.dumps(facts.model_dump(mode="json"), separators=(",", ":"))


def answer_facts(
    options: DisparityOptions,
    result: JobResult[StereoMaps],
    weights: str,
    trained: bool,
    size: ImageHeader,
    rectifier: Rectifier | None,
) -> AnswerFacts:
    """What the answer says of its computation (`AnswerFacts`).

    result: the request's maps and timings; weights: the weights' identity
    (`service.batching.runtime.weights_identity`); trained: whether the model's weights are trained
    (`Predictor.trained`); size: the input images' size; rectifier: a raw pair's (None for a
    rectified pair).
    """
    offset = result.output.row_offset
    return AnswerFacts(
        model=options.model,
        model_status="trained" if trained else "untrained",
        weights=weights,
        image_size=ImageSize(width=size.width, height=size.height),
        batch_size=result.batch_size,
        timings=Timings(
            queue_ms=round(result.queue_seconds * 1000, 2), compute_ms=round(result.compute_seconds * 1000, 2)
        ),
        frame=options.frame if rectifier is not None else Frame.rectified,
        camera=None if rectifier is None else rectified_camera(rectifier),
        row_offset=None if offset is None else row_offset_report(offset),
    )


def response_body(
    options: DisparityOptions,
    result: JobResult[StereoMaps],
    left: np.ndarray,
    facts: AnswerFacts,
    rectifier: Rectifier | None = None,
) -> tuple[bytes, str]:
    """The body of the answer in `options.format`, and its media type; every format carries `facts`
    (`format=json` as its fields, the others as `facts_text` inside the file).

    result: the request's maps (float32 HxW: disparity in px of the left image the network saw,
    uncertainty in [0, 1]); left: that left image, uint8 HxWx3 RGB (colours of the point cloud);
    rectifier: a raw pair's (it gives the focal length and baseline, and with `frame=original` the
    maps are resampled into the original left image's pixels).
    """
    outputs = PredictionOutputs(
        result.output.disparity,
        result.output.uncertainty,
        left,
        OutputOptions(
            focal_baseline=options.focal_baseline if rectifier is None else rectifier.focal_baseline,
            limits=DepthRange(options.min_disparity, options.max_depth_m),
            rectifier=rectifier,
            original=options.frame is Frame.original,
            color_min=options.color_min,
            color_max=options.color_max,
            max_uncertainty=options.max_uncertainty,
        ),
    )
    disparity, uncertainty, depth = outputs.maps
    text = facts_text(facts)
    match options.format:
        case OutputFormat.json:
            body = DisparityResponse(
                **dict(facts),
                disparity=encode_array(disparity),
                uncertainty=encode_array(uncertainty),
                depth=None if depth is None else encode_array(depth),
            )
            return body.model_dump_json().encode(), "application/json"
        case OutputFormat.npz:
            maps = {"disparity": disparity, "uncertainty": uncertainty}
            if depth is not None:
                maps["depth"] = depth
            return encode_npz(maps, text), "application/x-npz"
        case OutputFormat.png:
            shown, disparity_range = outputs.colored_disparity()
            png = encode_preview(shown, uncertainty, disparity_range)
        case OutputFormat.disparity_png16:
            png = encode_png16(disparity, KITTI_SCALE)
        case OutputFormat.depth_png16:
            assert depth is not None  # DisparityOptions requires the calibration for it
            png = encode_png16(depth, KITTI_SCALE)
        case OutputFormat.uncertainty_png16:
            png = encode_png16(uncertainty, UNCERTAINTY_SCALE)
        case OutputFormat.ply:
            return outputs.ply(comments=[f"{FACTS} {text}"]), "application/x-ply"
    return png_with_text(png, FACTS, text), "image/png"


def rectified_camera(rectifier: Rectifier) -> RectifiedCamera:
    """The rectified left camera of a raw pair's rig."""
    camera = rectifier.focal_baseline
    assert camera.cx is not None and camera.cy is not None  # a rig always has its principal point
    return RectifiedCamera(focal_px=camera.focal_px, baseline_m=camera.baseline_m, cx_px=camera.cx, cy_px=camera.cy)


def row_offset_report(offset: RowOffset) -> RowOffsetReport:
    """A measured row offset as answers give it, to a thousandth of a pixel."""
    return RowOffsetReport(
        centre_px=round(offset.centre_px, 3),
        across_px=round(offset.across_px, 3),
        down_px=round(offset.down_px, 3),
        largest_px=round(offset.largest_px, 3),
        tracks=offset.tracks,
        aligned=offset.aligned,
    )


def encode_array(values: np.ndarray) -> EncodedArray:
    """float32 little-endian raw bytes, base64."""
    raw = np.ascontiguousarray(values, dtype="<f4").tobytes()
    return EncodedArray(shape=values.shape, data=base64.b64encode(raw).decode("ascii"))


def encode_npz(maps: dict[str, np.ndarray], facts: str) -> bytes:
    """An npz of float32 `maps` and the 0-d string array `facts` (`facts_text`)."""
    buffer = io.BytesIO()
    # maps and a string, so no pickling; naming the keyword also keeps `**` off it for mypy
    np.savez(buffer, allow_pickle=False, **maps, **{FACTS: np.array(facts)})
    return buffer.getvalue()


def encode_preview(disparity: np.ndarray, uncertainty: np.ndarray, disparity_range: tuple[float, float]) -> bytes:
    """RGB PNG (`stereo_data.visualize.preview`): disparity (turbo, over `disparity_range` px)
    left of uncertainty (inferno, 0-1), each with a colour bar that prints its range."""
    return encode_png(preview(disparity, uncertainty, disparity_range))
