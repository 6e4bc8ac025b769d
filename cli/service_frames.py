"""`crestereo-pp predict --url`: a job's pairs computed by a running service instead of a model here."""

from __future__ import annotations

from typing import Any

import httpx
import numpy as np

from crestereo_pp.client import DisparityResult, DisparityStream, ServiceError, StereoClient
from crestereo_pp.inference import InferenceOptions


class ServiceFrames:
    """The pairs of one job sent to the service at `url` (`crestereo-pp serve`, the container), with
    the command's model and options: each pair on its own (`POST /disparity`), or with `sequence`
    the frames of one camera over one stream (`/disparity/stream`), each warm-started from the
    previous one with `warm_iters` iterations. `predict` and `restart` as `FrameStream`'s; a
    service that refuses or cannot be reached is a ConnectionError saying so."""

    def __init__(
        self,
        url: str,
        api_key: str | None,
        model: str,
        options: InferenceOptions,
        sequence: bool,
        warm_iters: int | None,
    ) -> None:
        self._url = url
        self._client = StereoClient(url, api_key=api_key)
        self._options: dict[str, Any] = {"model": model, **options.keywords()}
        self._sequence, self._warm_iters = sequence, warm_iters
        self._stream: DisparityStream | None = None

    def predict(self, left: np.ndarray, right: np.ndarray) -> DisparityResult:
        """The maps of the next pair (RGB arrays), computed by the service."""
        try:
            if not self._sequence:
                return self._client.disparity(left, right, **self._options)
            if self._stream is None:
                self._stream = self._client.stream(warm_iters=self._warm_iters, **self._options)
            return self._stream.send(left, right)
        except ServiceError as error:
            raise ConnectionError(f"the service at {self._url} answered {error}") from None
        except (httpx.HTTPError, OSError) as error:
            raise ConnectionError(f"no answer from the service at {self._url}: {error}") from None

    def restart(self) -> None:
        """Forget the previous frame: the next pair is computed cold (a new stream)."""
        if self._stream is not None:
            self._stream.close()
            self._stream = None

    def close(self) -> None:
        self.restart()
        self._client.close()
