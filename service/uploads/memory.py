"""glibc's malloc in the server process: its arenas capped (`limit_malloc_arenas`), and the memory
that streams and requests leave free given back to the system once they end (`FreedMemory`). Off
glibc both do nothing."""

from __future__ import annotations

import asyncio
import ctypes
import os
from collections.abc import Callable
from typing import Any

MALLOC_ARENAS = 2
"""glibc malloc arenas of the server process (glibc's default: 8 per core). Each thread that
allocates (the inference thread, OpenVINO's and the response threads) gets an arena of its own up to that
limit, and what one frees stays in it for that arena's next allocations: under a mix of image sizes
16 arenas held 550-800 MiB free (and growing) beside about 1 GiB in use."""
M_ARENA_MAX = -8  # mallopt's parameter number (malloc.h)

TRIM_DELAY_S = 0.5
"""After a stream ends, the memory malloc holds free is given back this much later, once for all
the streams that ended meanwhile."""
IDLE_TRIM_DELAY_S = 2.0
"""After the last request in progress ends, the memory malloc holds free is given back this much
later, unless another request has begun: a client that sends a pair every second or two never waits
for its pages to be faulted back in."""


def _libc() -> Any | None:
    """The C library of this process where it is glibc (it has `mallopt` and `malloc_trim`), else None."""
    try:
        libc = ctypes.CDLL(None)
        libc.mallopt, libc.malloc_trim  # noqa: B018 - glibc's, absent elsewhere
    except (OSError, AttributeError):
        return None
    return libc


def limit_malloc_arenas(arenas: int = MALLOC_ARENAS) -> bool:
    """Cap glibc's malloc arenas in this process at `arenas` (mallopt M_ARENA_MAX), before the
    server starts its threads, unless MALLOC_ARENA_MAX is set (glibc read that at startup: it wins).
    Returns whether the cap was set (False off glibc)."""
    libc = _libc()
    if "MALLOC_ARENA_MAX" in os.environ or libc is None:
        return False
    return bool(libc.mallopt(M_ARENA_MAX, arenas))


class FreedMemory:
    """Gives the memory malloc holds free back to the system (`malloc_trim`), a delay after `soon`
    is called, once for every call meanwhile. What a stream's images or a request's work leave
    free, glibc keeps in its heap for later allocations (its mmap threshold rises to the largest
    buffer freed, and the network's buffers of each image size fragment it): 12 streams closed at
    their budget left about 250 MiB in the process's resident memory until others reused it, and
    a burst of 54 image sizes left it 173-342 MiB above where it was, against 33-100 given back."""

    def __init__(self) -> None:
        self._libc = _libc()
        self._pending: asyncio.TimerHandle | None = None
        self._vetoes: list[Callable[[], bool]] = []

    def soon(self, delay_s: float = TRIM_DELAY_S, unless: Callable[[], bool] | None = None) -> None:
        """Trim `delay_s` from now (call on the event loop), or at the trim already due sooner,
        unless `unless()` is true by then, for this call's `unless` or that of any other call
        meanwhile (new work began: the trim would only have it fault the pages back in)."""
        if self._libc is None:
            return
        if unless is not None and unless not in self._vetoes:  # one bound method: once
            self._vetoes.append(unless)
        loop = asyncio.get_running_loop()
        due = loop.time() + delay_s
        if self._pending is not None:
            if self._pending.when() <= due:
                return
            self._pending.cancel()
        self._pending = loop.call_at(due, self._trim)

    def _trim(self) -> None:
        vetoed = any(veto() for veto in self._vetoes)
        self._pending = None
        self._vetoes.clear()
        if self._libc is not None and not vetoed:
            self._libc.malloc_trim(0)
