"""`GET /models` and `GET /models/{name}`: what each served model is (Open Inference Protocol
model metadata, plus parameters, iterations, uncertainty meaning, training record and limits)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

from crestereo_pp.service.api.dependencies import API_KEY_SCHEME, RuntimeDep
from crestereo_pp.service.api.disparity_docs import RESPONSES
from crestereo_pp.service.api.errors import ApiError
from crestereo_pp.service.api.schemas import ErrorResponse, ModelInfo, ModelList, TensorMetadata, TrainingSummary
from crestereo_pp.service.batching.runtime import ServiceRuntime, weights_identity
from crestereo_pp.service.batching.stereo import Predictor

router = APIRouter(tags=["models"])

_IMAGE = [-1, -1, 3]  # height, width, RGB; grey images are accepted too (repeated to RGB)
_MAP = [-1, -1]
INPUTS = [
    TensorMetadata(name="left", datatype="UINT8", shape=_IMAGE),
    TensorMetadata(name="right", datatype="UINT8", shape=_IMAGE),
]
OUTPUTS = [
    TensorMetadata(name="disparity", datatype="FP32", shape=_MAP),
    TensorMetadata(name="uncertainty", datatype="FP32", shape=_MAP),
]


@router.head("/models", include_in_schema=False)
@router.get(
    "/models",
    summary="The models this server has loaded",
    response_model=ModelList,
    responses={401: RESPONSES[401]},
    # `{}` beside the bearer scheme: the key is optional (only when CRESTEREO_API_KEY is set).
    openapi_extra={"security": [{}]},
    dependencies=[API_KEY_SCHEME],
)
async def list_models(runtime: RuntimeDep) -> ModelList:
    """Every loaded model (none while loading)."""
    return ModelList(models=[model_info(runtime, name) for name in runtime.predictors])


@router.head("/models/{name}", include_in_schema=False)
@router.get(
    "/models/{name}",
    summary="One loaded model",
    response_model=ModelInfo,
    responses={401: RESPONSES[401], 404: {"model": ErrorResponse, "description": "No such model on this server."}},
    openapi_extra={"security": [{}]},
    dependencies=[API_KEY_SCHEME],
)
async def get_model(name: str, runtime: RuntimeDep) -> ModelInfo:
    if name not in runtime.predictors:
        raise ApiError(
            404,
            "model_not_found",
            f"no model `{name}` on this server (loaded: {', '.join(runtime.predictors) or 'none yet'})",
        )
    return model_info(runtime, name)


def model_info(runtime: ServiceRuntime, name: str) -> ModelInfo:
    predictor = runtime.predictors[name]
    settings = runtime.settings
    compiled = predictor.ready()
    return ModelInfo(
        name=name,
        versions=[weights_identity(predictor)],
        platform="openvino" if predictor.backend == "openvino" and compiled else "pytorch",
        inputs=INPUTS,
        outputs=OUTPUTS,
        status="trained" if predictor.trained else "untrained",
        parameters=predictor.num_parameters,
        backend=predictor.backend,
        precision=predictor.precision,
        compiled=compiled,
        iterations=list(predictor.config.iters),
        uncertainty=uncertainty_meaning(predictor),
        training=training_summary(predictor.training),
        max_image_pixels=settings.pixel_limit(name),
        min_image_side=settings.min_image_side,
        max_request_cost=settings.max_request_cost,
    )


def uncertainty_meaning(predictor: Predictor) -> str:
    calibration = predictor.calibration
    if calibration is None:
        return "the paper's U of the last iteration, in [0, 1] (no calibration in these weights)"
    return f"P(|disparity error| > {calibration.threshold_px:g} px), calibrated on {calibration.fitted_on}"


def training_summary(training: dict[str, Any] | None) -> TrainingSummary | None:
    if not training:
        return None
    runs = training.get("runs") or []
    validations = [run["validation"] for run in runs if run.get("validation")]
    return TrainingSummary(
        steps=int(training.get("total_steps", 0)),
        pairs=int(training.get("total_pairs", 0)),
        minutes=round(float(training.get("total_minutes", 0.0)), 1),
        dev_metrics={key: round(float(value), 3) for key, value in validations[-1].items()} if validations else None,
    )
