"""The HTTP contract: request options and response bodies as pydantic models."""

from __future__ import annotations

import re
from collections.abc import Mapping
from enum import StrEnum
from typing import Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    FiniteFloat,
    ModelWrapValidatorHandler,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic.fields import FieldInfo
from pydantic_core import ErrorDetails, InitErrorDetails, PydanticCustomError

from crestereo_pp.inference.options import (
    ITERATIONS_PATTERN,
    InferenceOptions,
    TwoPass,
    parse_iterations,
    parse_two_pass,
)
from crestereo_pp.inference.scaling import scaled_size
from crestereo_pp.model.config import ModelName
from crestereo_pp.stereo_data.pointcloud import MIN_DISPARITY, FocalBaseline
from crestereo_pp.stereo_data.rig import MAX_IMAGE_SIDE, focal_baseline_problem
from crestereo_pp.stereo_data.visualize import color_scale_problem


class OutputFormat(StrEnum):
    """How `POST /disparity` returns its maps."""

    json = "json"
    npz = "npz"
    png = "png"
    disparity_png16 = "disparity_png16"
    uncertainty_png16 = "uncertainty_png16"
    depth_png16 = "depth_png16"
    ply = "ply"


class Frame(StrEnum):
    """The pixel grid of the maps of a raw pair sent with its calibration."""

    rectified = "rectified"
    original = "original"


_DECIMAL = re.compile(r"[+-]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]+)?")
_BOUND_WORDS = {"gt": "above", "ge": "at least", "lt": "below", "le": "at most"}
"""How a number option's constraints read in its error: `scale` must be above 0 and at most 1."""


TrainingStatus = Literal["trained", "untrained"]
"""`untrained`: the weights have no validation on real pairs within 50 % bad-2; their maps are not usable."""


class DisparityOptions(BaseModel):
    """Query parameters of `POST /disparity` (options go in the query string, never the form)."""

    model_config = ConfigDict(extra="forbid")

    model: ModelName = Field("lite", description="Network: `lite` (fast) or `full` (accurate).")
    format: OutputFormat = Field(
        OutputFormat.json,
        description="`json`: maps as base64 little-endian float32 with shape and dtype. "
        "`npz`: numpy archive of the maps. `png`: colour preview, disparity (turbo colour map over "
        "the map's 1st-99th percentile, or `color_min`-`color_max` px) beside uncertainty "
        "(inferno, 0 to 1), each with a colour bar printing its range. `disparity_png16`: KITTI "
        "16-bit PNG, value = round(disparity x 256), 0 = invalid, clipped at 65535. "
        "`depth_png16`: KITTI depth 16-bit PNG, value = round(metres x 256), 0 = invalid, needs "
        "a `calibration` part, or `focal_px` and `baseline_m`. `uncertainty_png16`: 16-bit PNG, value = "
        "round(uncertainty x 65535). `ply`: binary PLY point cloud coloured by the left image: "
        "metric (metres, left camera frame) with a `calibration` part (the rectified left camera), or "
        "with `focal_px` and `baseline_m` (principal point `cx_px`, `cy_px`, default the image centre), "
        "else image-space (x px, y px, disparity px); "
        "pixels above `max_uncertainty` are dropped.",
    )
    two_pass: TwoPass = Field(
        "auto",
        description="Cascaded inference, a half-resolution pass initialising the full-resolution one "
        "(finds large disparities, coarser on fine detail): `true`, `false`, or `auto`: a quick "
        "quarter-resolution pass decides: two passes where it finds disparities above about 90 px, one "
        "elsewhere, either way on the pair enlarged 1.5x or 1.25x as far as the pass that finds the "
        "disparities still holds their range (finer matching, up to 2.25x the time; never past 1.2 M "
        "pixels, nor at `scale` < 1), or shrunk where they are too large even for two passes (above "
        "about 280 px).",
    )
    iters: str | None = Field(
        None,
        pattern=ITERATIONS_PATTERN,
        examples=["4", "1,2,4"],
        description="ARM iterations: `N` at 1/4 resolution, or `N16,N8,N4` for the three stages "
        "(1-99 each); fewer is faster and coarser [the model's: lite 2,4,6, full 2,4,8].",
    )
    scale: FiniteFloat = Field(
        1.0,
        gt=0,
        le=1,
        description="Run the network on the pair resized by this factor (0 < "
        "scale <= 1): about scale^2 of the network's time (the classical steps stay at the pair's size: 0.5 "
        "takes 0.4-0.5 of the time of 1 on a CPU); the maps still come at the input's size, "
        "disparity in input pixels.",
    )
    raw_uncertainty: bool = Field(
        False,
        description="Return the paper's raw U (last iteration, in [0, 0.5] after the first) "
        "instead of the calibrated probability of an error above 2 px (see `uncertainty`).",
    )
    flip: bool = Field(
        False,
        description="Also compute the pair upside down and merge the two answers (their mean where they "
        "agree within 2 px, else the less uncertain one; the uncertainty is the mean of the two): about "
        "twice the time, fewer errors.",
    )
    blend_sgbm: bool = Field(
        True,
        description="Average the network's answer with OpenCV's semi-global matcher (SGBM) where SGBM has an "
        "answer within 4 px of it (a pixel moves by at most 2 px): fewer errors over 1 and 2 px for one SGBM "
        "run more (about 5 % of the default's time on a CPU). The uncertainty stays the network answer's.",
    )
    refine_edges: bool = Field(
        True,
        description="Refine the answer at its edges. Its depth edges are put where the left image's colour edges "
        "are: near a depth edge, each pixel takes the median of the disparities around it weighted by how alike "
        "their colours are (and how near). Then the strip along the image's left edge whose matches fall outside "
        "the right image is raised towards the disparity of the surface beside it, by 4 px at most. Fewer errors "
        "at the edges of objects and of the image, under 10 % more time on a CPU. With `blend_sgbm=false` too, "
        "the network's own answer is served. The uncertainty stays the network answer's.",
    )
    align_rows: bool = Field(
        True,
        description="Where the right image's rows are off the left's by a quarter pixel or more, resample it onto "
        "them first. The offset is measured on the pair itself: corners of the left image tracked into the right "
        "one, their vertical offsets fitted as a plane (a shift and two tilts). Real rectifications leave a few "
        "tenths of a pixel, a drifted calibration whole pixels, and 1 px doubles the network's errors; about "
        "20 ms a pair.",
    )
    color_min: FiniteFloat | None = Field(
        None,
        ge=-MAX_IMAGE_SIDE,
        le=MAX_IMAGE_SIDE,
        description="`format=png`: disparity (px) at the bottom of the colour scale [the map's 1st percentile].",
    )
    color_max: FiniteFloat | None = Field(
        None,
        ge=-MAX_IMAGE_SIDE,
        le=MAX_IMAGE_SIDE,
        description="`format=png`: disparity (px) at the top of the colour scale [the map's 99th percentile].",
    )
    cx_px: FiniteFloat | None = Field(None, description="`format=ply`: principal point x in px [the image centre].")
    cy_px: FiniteFloat | None = Field(None, description="`format=ply`: principal point y in px [the image centre].")
    max_uncertainty: FiniteFloat | None = Field(
        None,
        ge=0,
        le=1,
        description="`format=ply`: drop points whose uncertainty (a probability, 0 to 1) is above this.",
    )
    frame: Frame = Field(
        Frame.rectified,
        description="With a `calibration` part (a raw pair): the maps in the rectified left image "
        "(`rectified`, what the network saw), or resampled into the original left image's pixels "
        "(`original`, to overlay on the camera's image; depth along that camera's own axis; disparity and "
        "depth +inf, uncertainty 1, where a pixel has no rectified counterpart). Point clouds are always in "
        "the rectified left camera's frame.",
    )
    focal_px: FiniteFloat | None = Field(
        None,
        gt=0,
        description="Focal length in pixels; with `baseline_m` adds a metric depth "
        "map Z = focal_px x baseline_m / disparity (invalid where disparity <= 0).",
    )
    baseline_m: FiniteFloat | None = Field(None, gt=0, description="Stereo baseline in metres; see `focal_px`.")
    min_disparity: FiniteFloat = Field(
        MIN_DISPARITY,
        ge=0,
        description="Depth and point clouds: pixels whose disparity is at or below this (px) give no depth and no "
        "point (depth there is beyond what matching resolves, and runs off to infinity at 0).",
    )
    max_depth_m: FiniteFloat | None = Field(
        None,
        gt=0,
        description="Depth and metric point clouds: pixels deeper than this (metres) give no depth and no point.",
    )

    @field_validator(
        "scale",
        "color_min",
        "color_max",
        "cx_px",
        "cy_px",
        "max_uncertainty",
        "focal_px",
        "baseline_m",
        "min_disparity",
        "max_depth_m",
        mode="before",
    )
    @classmethod
    def _plain_decimal(cls, value: object) -> object:
        """Numbers in the query are plain decimals: `1_0` or `0x1p-3` are refused, not read as 10 or 0.125."""
        if isinstance(value, str) and not _DECIMAL.fullmatch(value):
            raise ValueError(f"expected a decimal number such as 0.5 or 1e-3, got {value[:32]!r}")
        return value

    @field_validator("iters", mode="before")
    @classmethod
    def _iterations(cls, value: object) -> object:
        """`iters` as ITERATIONS_PATTERN spells the counts `parse_iterations` reads (its message
        where they are not 1 or 3 counts of 1-99): `04`, ` 4` or `1_0` are refused, not read as 4 or 10."""
        if isinstance(value, str) and not re.fullmatch(ITERATIONS_PATTERN, value):
            parse_iterations(value)  # raises for wrong counts, with the message the CLI gives
            raise ValueError(
                f"iterations are plain counts without leading zeros, such as 4 or 1,2,4, got {value[:32]!r}"
            )
        return value

    @field_validator("two_pass", mode="before")
    @classmethod
    def _two_pass(cls, value: object) -> object:
        """`two_pass` spelled as on the command line (`parse_two_pass`, its message where it is not)."""
        return parse_two_pass(value) if isinstance(value, str | bool) else value

    @property
    def focal_baseline(self) -> FocalBaseline | None:
        """The camera of `focal_px`, `baseline_m`, `cx_px`, `cy_px`; None without one."""
        if self.focal_px is None or self.baseline_m is None:
            return None
        return FocalBaseline(self.focal_px, self.baseline_m, self.cx_px, self.cy_px)

    @property
    def inference(self) -> InferenceOptions:
        """The options that say how the pair is computed (`inference.InferenceOptions`, which parses
        `iters`): read once per request, where the pipeline keys it (`answer_pair`), or once per stream."""
        return InferenceOptions(
            self.iters,
            self.two_pass,
            self.scale,
            self.raw_uncertainty,
            self.flip,
            self.blend_sgbm,
            self.refine_edges,
            self.align_rows,
        )

    def scale_problem(self, height: int, width: int) -> str | None:
        """What is wrong with `scale` for a pair of this size (None: nothing)."""
        try:
            scaled_size(height, width, self.scale)
        except ValueError as exc:
            return str(exc)
        return None

    def calibration_problem(self, calibrated: bool) -> str | None:
        """What is wrong with these options for a pair sent with (`calibrated`) or without a
        `calibration` part (None: nothing). Checked once the form is read."""
        if calibrated and (self.focal_px is not None or self.cx_px is not None or self.cy_px is not None):
            return (
                "the calibration part gives the focal length, baseline and principal point: "
                "leave out focal_px, baseline_m, cx_px and cy_px"
            )
        if not calibrated and self.frame is Frame.original:
            return "frame=original needs a `calibration` part (a rectified pair has no other frame)"
        needs = "a `calibration` part, or focal_px and baseline_m"
        if not calibrated and self.focal_px is None:
            if self.format is OutputFormat.depth_png16:
                return f"format=depth_png16 needs {needs}"
            if self.max_depth_m is not None:
                return f"max_depth_m needs {needs}"
            if "min_disparity" in self.model_fields_set and self.format is not OutputFormat.ply:
                return f"min_disparity needs {needs}, or format=ply (it bounds depth and point clouds)"
            if self.cx_px is not None or self.cy_px is not None:
                return "cx_px and cy_px need focal_px and baseline_m"
        return None

    @model_validator(mode="after")
    def _consistent(self) -> DisparityOptions:
        if (self.focal_px is None) != (self.baseline_m is None):
            raise ValueError("give both focal_px and baseline_m, or neither")
        problem = color_scale_problem(self.color_min, self.color_max)
        if problem is not None:
            raise ValueError(problem)
        if self.focal_px is not None and self.baseline_m is not None:
            problem = focal_baseline_problem(self.focal_px, self.baseline_m, "focal_px x baseline_m")
            if problem is not None:
                raise ValueError(problem)
        return self

    @model_validator(mode="wrap")
    @classmethod
    def _plain_errors(cls, data: object, handler: ModelWrapValidatorHandler[DisparityOptions]) -> DisparityOptions:
        """Pydantic's errors as sentences that say what the option takes (`_option_problem`): the
        same on `POST /disparity` and `/disparity/stream`, which both validate the query here.
        Defined last, so that it wraps the validators above (`_consistent`'s errors too)."""
        try:
            return handler(data)
        except ValidationError as error:
            problems = [
                InitErrorDetails(
                    type=PydanticCustomError(detail["type"], _option_problem(detail, cls.model_fields)),
                    loc=detail["loc"],
                    input=detail["input"],
                )
                for detail in error.errors()
            ]
            raise ValidationError.from_exception_data(error.title, problems) from None


def _option_problem(error: ErrorDetails, options: Mapping[str, FieldInfo]) -> str:
    """One of pydantic's errors about a query option as a sentence that says what the option takes;
    the others as pydantic words them (a validator's ValueError: its message after "Value error, ",
    which `errors.validation_problems` drops)."""
    given = f"got {str(error['input'])[:32]!r}"
    match error["type"]:
        case "extra_forbidden":
            return f"unknown option; the options are {', '.join(options)}"
        case "greater_than" | "greater_than_equal" | "less_than" | "less_than_equal":
            return f"must be {_bounds(options[str(error['loc'][0])])}, {given}"
        case "bool_parsing":
            return f"must be true or false (or 1 or 0, yes or no, on or off), {given}"
    return error["msg"]


def _bounds(option: FieldInfo) -> str:
    """The range a number option takes, from its constraints: `above 0 and at most 1`."""
    return " and ".join(
        f"{words} {getattr(constraint, bound):g}"
        for constraint in option.metadata
        for bound, words in _BOUND_WORDS.items()
        if getattr(constraint, bound, None) is not None
    )


class EncodedArray(BaseModel):
    """A 2-D array as base64 of its raw little-endian bytes, row-major."""

    dtype: Literal["float32"] = "float32"
    byte_order: Literal["little"] = "little"
    shape: tuple[int, int] = Field(description="[height, width]")
    data: str = Field(description="base64 of the raw bytes")


class ImageSize(BaseModel):
    width: int
    height: int


class Timings(BaseModel):
    """Where the server spent the request's time, in milliseconds."""

    queue_ms: float = Field(description="From queueing (after decoding) until the batch started.")
    compute_ms: float = Field(description="Network time of the whole batch the request ran in.")


class RectifiedCamera(BaseModel):
    """The rectified left camera of a raw pair: depth = focal_px x baseline_m / disparity, and pixel
    (x, y) of the rectified image looks along ((x - cx_px) / focal_px, (y - cy_px) / focal_px, 1)."""

    focal_px: float
    baseline_m: float
    cx_px: float
    cy_px: float


class RowOffsetReport(BaseModel):
    """How far the right image's rows lay off the left's, measured on the pair before matching (from
    corners tracked between the images): a left pixel's match lay dy px lower in the right image
    (negative: higher), dy(x, y) = centre_px + across_px * (x / W - 1/2) + down_px * (y / H - 1/2).
    A well-rectified pair stays within a few tenths of a pixel; a pixel or more says that the
    rig's calibration is off."""

    centre_px: float = Field(description="dy at the image's centre.")
    across_px: float = Field(description="How much dy grows from the left edge to the right one (a turn).")
    down_px: float = Field(description="How much dy grows from the top to the bottom (a focal length mismatch).")
    largest_px: float = Field(description="The largest |dy| over the image (at one of its corners).")
    tracks: int = Field(description="Corners the offset was fitted to.")
    aligned: bool = Field(
        description="Whether the right image was resampled onto the left's rows before matching (where "
        "`largest_px` is 0.25 or more)."
    )


class AnswerFacts(BaseModel):
    """What an answer says of its computation, in every format: the fields of a `format=json` body
    but its maps; also as `X-*` headers, and inside the file of the other formats as one line of
    this JSON (an npz's 0-d string array `facts`, a PNG's tEXt chunk `facts`, a PLY's header line
    `comment facts {...}`)."""

    model: ModelName
    model_status: TrainingStatus = Field(
        description="`untrained`: the model's maps are not usable (see `GET /models`); as `X-Model-Status`."
    )
    weights: str = Field(description="First 16 hex digits of the weights' sha256, or `random-init`.")
    image_size: ImageSize
    batch_size: int = Field(description="How many requests were computed together with this one.")
    timings: Timings
    frame: Frame = Field(Frame.rectified, description="The pixel grid of the maps (see the `frame` option).")
    camera: RectifiedCamera | None = Field(
        None,
        description="With a calibration part: the rectified left camera that disparity and depth refer to "
        "(as `X-Camera`).",
    )
    row_offset: RowOffsetReport | None = Field(
        None,
        description="With `align_rows` (the default): the right image's row offset as measured (as "
        "`X-Row-Offset`); null where the pair has too little texture to measure it, or with `align_rows=false`.",
    )


class DisparityResponse(AnswerFacts):
    """Body of a `format=json` answer: what it says of its computation (the facts every format
    carries) and its maps."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "model": "lite",
                    "model_status": "trained",
                    "weights": "9f2c4e1a7b3d5c60",
                    "image_size": {"width": 2, "height": 1},
                    "batch_size": 3,
                    "timings": {"queue_ms": 12.5, "compute_ms": 481.3},
                    "frame": "rectified",
                    "camera": None,
                    "row_offset": None,
                    "disparity": {"dtype": "float32", "byte_order": "little", "shape": [1, 2], "data": "AAAgQQAAJEE="},
                    "uncertainty": {
                        "dtype": "float32",
                        "byte_order": "little",
                        "shape": [1, 2],
                        "data": "zczMPc3MTD4=",
                    },
                    "depth": None,
                }
            ]
        }
    )

    disparity: EncodedArray = Field(description="Pixels of the left image, positive; x_right = x - d.")
    uncertainty: EncodedArray = Field(
        description="Per-pixel probability that the disparity is off "
        "by more than 2 px, calibrated for the served weights on "
        "procedural scenes (see the model card); with "
        "`raw_uncertainty=true`, or for weights without a "
        "calibration, the paper's U in [0, 1]."
    )
    depth: EncodedArray | None = Field(
        None,
        description="Metres, +inf where there is no depth (disparity <= min_disparity, or beyond max_depth_m); "
        "only with a calibration part, or focal_px and baseline_m.",
    )


class ErrorDetail(BaseModel):
    code: str = Field(description="Stable machine-readable reason, e.g. `size_mismatch`.")
    message: str = Field(description="What was wrong, for humans.")


class ErrorResponse(BaseModel):
    """Body of every error answer."""

    error: ErrorDetail


ServiceState = Literal["loading", "ready", "draining", "failed"]


class ModelStatus(BaseModel):
    loaded: bool
    parameters: int | None = None
    weights: str | None = Field(None, description="As in `DisparityResponse.weights`.")


class BatchingConfig(BaseModel):
    max_batch_size: int
    max_batch_pixels: int
    max_wait_ms: float
    max_queue: int
    torch_threads: int


class HealthResponse(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "status": "ready",
                    "models": {
                        "lite": {"loaded": True, "parameters": 629624, "weights": "9f2c4e1a7b3d5c60"},
                        "full": {"loaded": True, "parameters": 5442712, "weights": "random-init"},
                    },
                    "queue_depth": {"lite": 3, "full": 0},
                    "batching": {
                        "max_batch_size": 8,
                        "max_batch_pixels": 131072,
                        "max_wait_ms": 10.0,
                        "max_queue": 32,
                        "torch_threads": 2,
                    },
                }
            ]
        }
    )

    status: ServiceState
    models: dict[str, ModelStatus]
    queue_depth: dict[str, int] = Field(description="Per model: requests admitted and not yet computing.")
    batching: BatchingConfig


class ProbeResponse(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{"status": "ready"}]})

    status: str = Field(description="`alive` / `dead` (liveness); the service state (readiness).")


class TensorMetadata(BaseModel):
    """An input or output of the model, as the Open Inference Protocol describes tensors."""

    name: str
    datatype: str
    shape: list[int] = Field(description="-1 for a free dimension.")


class TrainingSummary(BaseModel):
    steps: int
    pairs: int
    minutes: float
    dev_metrics: dict[str, float] | None = Field(
        None,
        description="Mean EPE (px), bad-1/2/3 and D1-all (%) on the real validation pairs, "
        "measured when these weights were saved (see the model card).",
    )


class ModelInfo(BaseModel):
    """One served model: Open Inference Protocol model metadata (`name`, `versions`, `platform`,
    `inputs`, `outputs`), then what this service adds."""

    name: str
    versions: list[str] = Field(description="The weights' identity, as `X-Weights`.")
    platform: Literal["pytorch", "openvino"] = Field(
        description="What computes requests with the default iterations now: `openvino` once `backend` is "
        "`openvino` and its graph is `compiled`, else `pytorch`."
    )
    inputs: list[TensorMetadata]
    outputs: list[TensorMetadata]
    status: TrainingStatus = Field(
        description="`untrained`: the weights have no validation on real pairs within 50 % bad-2; their "
        "maps are not usable (answers carry `X-Model-Status: untrained`). `training.dev_metrics` has the numbers."
    )
    parameters: int
    backend: Literal["torch", "openvino"] = Field(
        description="What computes the maps: `openvino` (compiled for the CPU) or `torch`."
    )
    precision: Literal["fp32", "bf16"]
    compiled: bool = Field(
        description="Whether requests with the default iterations run on `backend` now. False while OpenVINO "
        "is still compiling them (once per weights, in the background, from the first request; about a "
        "minute): torch answers those meanwhile, with the same maps."
    )
    iterations: list[int] = Field(description="Default ARM iterations at 1/16, 1/8, 1/4.")
    uncertainty: str = Field(description="What the `uncertainty` map means for these weights.")
    training: TrainingSummary | None = Field(None, description="None for weights without a record.")
    max_image_pixels: int
    min_image_side: int
    max_request_cost: float = Field(
        description="Most compute one request may ask for, in plain requests of a `max_image_pixels` image: "
        "its pixels times what its options cost (more iterations and `flip` cost more, a "
        "`scale` below 1 less); beyond it 422 `request_too_costly`."
    )


class ModelList(BaseModel):
    models: list[ModelInfo]
