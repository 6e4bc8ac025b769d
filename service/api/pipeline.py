"""The request pipeline `POST /disparity` and `/disparity/stream` share, from a pair whose image
headers have passed to its answer's body: admitted to its model's queue, decoded in a decoder
process, rectified where it is raw, computed in a batch, its body made in the answer's format.
The routes keep what differs: how the pair arrives (a multipart body, two WebSocket messages) and
how its answer leaves."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from starlette.concurrency import run_in_threadpool

from crestereo_pp.inference import WarmStart
from crestereo_pp.service.api.errors import bad_input
from crestereo_pp.service.api.response_bodies import answer_facts, response_body
from crestereo_pp.service.api.schemas import AnswerFacts, DisparityOptions
from crestereo_pp.service.batching.runtime import ServiceRuntime, StereoBatcher, weights_identity
from crestereo_pp.service.batching.stereo import (
    FALLBACK_COST,
    StereoKey,
    StereoPair,
    options_cost,
    stereo_key,
)
from crestereo_pp.service.uploads.images import ImageHeader
from crestereo_pp.service.uploads.multipart import Upload
from crestereo_pp.service.uploads.sandbox import Stop


@dataclass(frozen=True)
class Answer:
    """A computed pair: what its answer says of it (`AnswerFacts`), and the answer's body and media
    type."""

    facts: AnswerFacts
    body: bytes
    media_type: str


async def answer_pair(
    runtime: ServiceRuntime,
    batcher: StereoBatcher,
    options: DisparityOptions,
    upload: Upload,
    *,
    stop: Stop,
    is_disconnected: Callable[[], Awaitable[bool]],
    deadline: float | None = None,
    frames: WarmStart | None = None,
    request_id: str | None = None,
) -> Answer:
    """Compute the pair of `upload` (its image files, checked from their headers, and its rig
    where it is raw) with `options` on `batcher`, and make its answer.

    stop: resolves with the error to raise once the request is abandoned while its images are
    decoded or its rectifier built; is_disconnected: whether the client has gone (the batcher
    drops such requests); deadline: `time.monotonic()` by which the answer is due; frames: a
    stream's warm starts, made from `options.inference` (each pair starts from the previous one's
    disparity), None for a pair on its own. 422 `scale_too_small` before anything is admitted
    where `options.scale` leaves the network too little of the image, 422 `request_too_costly`
    where the pair and its options ask for more compute than the server allows one request
    (`cost_problem`); otherwise what admission, decoding and batching raise.
    """
    header = upload.header
    problem = options.scale_problem(header.height, header.width)
    if problem is not None:
        raise bad_input(422, "scale_too_small", problem)
    init = None if frames is None else frames.start(header.height, header.width)
    key = stereo_key(
        options.model,
        options.inference if frames is None or init is None else frames.warm_options,
        header.height,
        header.width,
        warm_start=init is not None,
    )
    problem = cost_problem(runtime, key, header)
    if problem is not None:
        raise bad_input(422, "request_too_costly", problem)
    # Admitted before a raw pair's rectifier is built: building one is work, bounded like decoding.
    async with (
        batcher.admit(options.model, key, deadline=deadline) as admission,
        runtime.rectifiers.use(upload.rig, stop) as rectifier,
    ):
        left, right = await runtime.decoders.decode_pair(upload.left, upload.right, header, stop)
        if rectifier is not None:  # a raw pair: the network sees it rectified
            left, right = await run_in_threadpool(rectifier.rectify, left, right)
        result = await admission.run(
            key,
            StereoPair(left, right, init),
            deadline=deadline,
            is_disconnected=is_disconnected,
            request_id=request_id,
        )
        if frames is not None:
            frames.record(result.output.disparity)
        predictor = runtime.predictors[options.model]
        facts = answer_facts(options, result, weights_identity(predictor), predictor.trained, header, rectifier)
        body, media_type = await run_in_threadpool(response_body, options, result, left, facts, rectifier)
    return Answer(facts, body, media_type)


def cost_problem(runtime: ServiceRuntime, key: StereoKey, header: ImageHeader) -> str | None:
    """What is wrong with the compute a pair of `header`'s size asks for with `key`'s options (None:
    nothing): at most `max_request_cost` plain requests of the model's largest image, counted as
    the pair's pixels times `options_cost`. One inference thread computes every request, so this
    bounds how long one small request (a few KB of flat PNGs) can hold it."""
    settings = runtime.settings
    limit = settings.pixel_limit(key.model)
    predictor = runtime.predictors[key.model]
    cost = options_cost(predictor, key.options, key.warm_start) * header.pixels / limit
    if cost <= settings.max_request_cost:
        return None
    slower = (
        ""
        if predictor.ready(key.options.iters, warm_start=key.warm_start)
        else f" (no fast graph is ready for these iterations, so torch computes them, about {FALLBACK_COST:g} "
        "times slower)"
    )
    return (
        f"this pair ({header.width}x{header.height}) with these options would cost {cost:.1f} times a plain request "
        f"of the largest image `{key.model}` takes ({limit} pixels){slower}; this server allows "
        f"{settings.max_request_cost:g}: ask for fewer iterations, no flip or a smaller scale, or send a smaller pair"
    )
