"""Raw pairs from a calibrated camera: a rectifier per calibration, built once and kept for the
next requests of the same camera (its maps cost up to about a second on large images)."""

from __future__ import annotations

import asyncio
from collections import OrderedDict

import cv2

from service.errors import bad_input
from stereo_data.rig import Rectifier, RigError, StereoRig

RECTIFIERS_KEPT = 4
"""Rectifiers kept (each holds about 24 bytes per pixel of maps)."""


class RectifierCache:
    """The rectifiers of the last `capacity` rigs, by the rig's JSON (`StereoRig.to_json`, as the
    decoder processes send it). Concurrent requests for one rig share one build."""

    def __init__(self, capacity: int = RECTIFIERS_KEPT) -> None:
        self.capacity = capacity
        self._builds: OrderedDict[str, asyncio.Future[Rectifier]] = OrderedDict()

    async def get(self, rig_json: str) -> Rectifier:
        """The rectifier of this rig; 422 `invalid_calibration` where it cannot be built."""
        build = self._builds.get(rig_json)
        if build is None:
            build = asyncio.ensure_future(asyncio.to_thread(_build, rig_json))
            self._builds[rig_json] = build
            while len(self._builds) > self.capacity:
                self._builds.popitem(last=False)
        else:
            self._builds.move_to_end(rig_json)
        try:
            return await asyncio.shield(build)  # a cancelled request leaves the build to the others
        except RigError as error:
            self._builds.pop(rig_json, None)
            raise bad_input(422, "invalid_calibration", f"calibration `{error.field}`: {error.reason}") from None


def _build(rig_json: str) -> Rectifier:
    rig = StereoRig.from_json(rig_json)
    try:
        return Rectifier(rig)
    except cv2.error as error:
        raise RigError("calibration", f"OpenCV cannot rectify these cameras ({error.err})") from None
