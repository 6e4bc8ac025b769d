"""Raw pairs from a calibrated camera: a rectifier per calibration, built once and kept for the
next requests of the same camera.

A rectifier's maps cost seconds of CPU and 24 bytes per pixel (96 MiB for a 2048x2048 camera), so
the cache bounds both: its rectifiers, those in use by requests and those kept, fit in
`max_bytes` (the least recently used unused one goes first; a request waits for room, or for
another build, under its deadline), and one is built at a time, on a thread. A request that gives
up waiting costs nothing more than a build already under way, whose rectifier is kept.
"""

from __future__ import annotations

import asyncio
from collections import OrderedDict
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass

import cv2

from crestereo_pp.service.api.errors import bad_input
from crestereo_pp.service.uploads.sandbox import Stop, unless
from crestereo_pp.stereo_data.rig import Rectifier, RigError, StereoRig

BYTES_PER_PIXEL = 24
"""What a rectifier holds per pixel: two float32 maps per camera, and float32 x, y back to the
original left image."""


@dataclass(eq=False)
class _Entry:
    build: asyncio.Task[Rectifier]
    nbytes: int
    users: int = 0  # requests holding it, or waiting for its build


class RectifierCache:
    """Rectifiers by the rig's JSON (`StereoRig.to_json`, as the decoder processes send it), in at
    most `max_bytes` of maps; concurrent requests for one rig share one build."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self._entries: OrderedDict[str, _Entry] = OrderedDict()  # least recently used first
        self._changed = asyncio.Event()  # set (and replaced) when a build ends or a rectifier is let go

    @property
    def held_bytes(self) -> int:
        """Bytes of the rectifiers held: in use, kept, or being built."""
        return sum(entry.nbytes for entry in self._entries.values())

    @asynccontextmanager
    async def use(self, rig_json: str | None, stop: Stop) -> AsyncIterator[Rectifier | None]:
        """The rectifier of this rig, in use during the block (None for None: a rectified pair).
        422 `invalid_calibration` where it cannot be built; `stop`'s exception where the request
        is abandoned before it is ready."""
        if rig_json is None:
            yield None
            return
        stopped = asyncio.ensure_future(stop())
        try:
            entry: _Entry = await unless(stopped, self._take(rig_json))
        except RigError as error:
            raise bad_input(422, "invalid_calibration", f"calibration `{error.field}`: {error.reason}") from None
        finally:
            stopped.cancel()
        try:
            yield entry.build.result()
        finally:
            self._let_go(entry)

    async def _take(self, rig_json: str) -> _Entry:
        """The rig's entry, built, with this request counted as a user."""
        nbytes = rectifier_bytes(StereoRig.from_json(rig_json))
        while True:
            entry = self._entries.get(rig_json)
            if entry is None and not self._building() and self._make_room(nbytes):
                entry = self._start(rig_json, nbytes)
            if entry is not None:
                self._entries.move_to_end(rig_json)
                entry.users += 1
                try:
                    await asyncio.shield(entry.build)  # a request that leaves leaves the build to the others
                except BaseException:
                    self._let_go(entry)
                    raise
                return entry
            await self._changed.wait()

    def _start(self, rig_json: str, nbytes: int) -> _Entry:
        entry = _Entry(asyncio.create_task(asyncio.to_thread(_build, rig_json)), nbytes)
        self._entries[rig_json] = entry
        entry.build.add_done_callback(lambda build: self._built(rig_json, entry))
        return entry

    def _built(self, rig_json: str, entry: _Entry) -> None:
        if entry.build.cancelled() or entry.build.exception() is not None:  # a rig OpenCV cannot rectify
            if self._entries.get(rig_json) is entry:
                del self._entries[rig_json]
        self._notify()

    def _let_go(self, entry: _Entry) -> None:
        entry.users -= 1
        self._make_room(0)
        self._notify()

    def _building(self) -> bool:
        return any(not entry.build.done() for entry in self._entries.values())

    def _make_room(self, nbytes: int) -> bool:
        """Give up unused rectifiers, least recently used first, until `nbytes` more fit; whether
        they do (or nothing is held: a rig larger than the whole cache is built alone)."""
        for rig_json, entry in list(self._entries.items()):
            if self.held_bytes + nbytes <= self.max_bytes:
                break
            if entry.users == 0 and entry.build.done():
                del self._entries[rig_json]
        return self.held_bytes + nbytes <= self.max_bytes or not self._entries

    def _notify(self) -> None:
        self._changed.set()
        self._changed = asyncio.Event()


def rectifier_bytes(rig: StereoRig) -> int:
    """Bytes of the maps of `rig`'s rectifier."""
    width, height = rig.image_size
    return width * height * BYTES_PER_PIXEL


def _build(rig_json: str) -> Rectifier:
    rig = StereoRig.from_json(rig_json)
    try:
        return Rectifier(rig)
    except cv2.error as error:
        raise RigError("calibration", f"OpenCV cannot rectify these cameras ({error.err})") from None
