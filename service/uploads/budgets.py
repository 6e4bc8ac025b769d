"""What the server holds at once, beyond the count of requests in progress: the bytes of uploads
(one budget for request bodies, another for stream images) and the open streams (in all, and per
client address). All are used on the event loop only, so a check and the take that follows it
cannot interleave with another's.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager

ENCODED_BYTES_PER_PIXEL = 8
"""The most an image file may take per pixel: 16-bit RGBA stored uncompressed (PNG, TIFF)."""
IMAGE_METADATA_BYTES = 1 << 20
"""Room for what an image file carries besides its pixels (EXIF, ICC profiles, chunk headers)."""


def largest_image_file(max_pixels: int, max_body_bytes: int) -> int:
    """Most bytes one image file of at most `max_pixels` pixels can take, and never more than a
    request body (which holds two)."""
    return min(max_body_bytes, max_pixels * ENCODED_BYTES_PER_PIXEL + IMAGE_METADATA_BYTES)


def largest_stream_image(max_pixels: int, max_body_bytes: int, max_stream_image_bytes: int) -> int:
    """Most bytes one image file (one WebSocket message) of a stream can take: the largest file of
    an image of at most `max_pixels` pixels, and never more than `max_stream_image_bytes`."""
    return min(max_stream_image_bytes, largest_image_file(max_pixels, max_body_bytes))


class ByteBudget:
    """At most `limit` bytes of `what` held at once: `take` before holding, `give_back` after."""

    def __init__(self, limit: int, what: str = "uploads") -> None:
        self.limit = limit
        self.what = what
        self.held = 0

    def fits(self, size: int) -> bool:
        """Whether `size` more bytes fit now."""
        return self.held + size <= self.limit

    def take(self, size: int) -> bool:
        """Reserve `size` bytes; False, with nothing reserved, when they do not fit."""
        if not self.fits(size):
            return False
        self.held += size
        return True

    def give_back(self, size: int) -> None:
        self.held -= size

    def refusal(self, size: int) -> str:
        """Why `size` more bytes were refused, for the client."""
        return (
            f"{self.held} bytes of {self.what} are held and {size} more would pass the {self.limit} "
            "this server holds at once; retry shortly"
        )


class StreamSlots:
    """At most `limit` streams open at once, and `per_client` from one client address."""

    def __init__(self, limit: int, per_client: int) -> None:
        self.limit = limit
        self.per_client = per_client
        self.open = 0
        self._by_client: Counter[str] = Counter()

    @contextmanager
    def place(self, client: str) -> Iterator[str | None]:
        """Hold a place for one stream of `client` during the block, and yield None; or yield
        why there is none (then nothing is held)."""
        refusal = self._refusal(client)
        if refusal is not None:
            yield refusal
            return
        self.open += 1
        self._by_client[client] += 1
        try:
            yield None
        finally:
            self.open -= 1
            self._by_client[client] -= 1
            if not self._by_client[client]:
                del self._by_client[client]

    def _refusal(self, client: str) -> str | None:
        if self._by_client[client] >= self.per_client:
            return f"{self._by_client[client]} streams are open from {client}, the most one client may open"
        if self.open >= self.limit:
            return f"{self.open} streams are open, the most this server takes at once"
        return None
