"""glibc's malloc in the server process: its arenas capped (`limit_malloc_arenas`), and the memory
that large uploads leave free given back to the system (`FreedMemory`). Off glibc both do nothing."""

from __future__ import annotations

import asyncio
import ctypes
import os
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
    """Gives the memory malloc holds free back to the system (`malloc_trim`), TRIM_DELAY_S after
    `soon` is first called, once for every call meanwhile. A stream's image is one large buffer;
    freed, glibc keeps it in its heap for later allocations (its mmap threshold rises to the
    largest buffer freed), so that 12 streams closed at their budget left about 250 MiB in the
    process's resident memory until others reused it."""

    def __init__(self) -> None:
        self._libc = _libc()
        self._pending: asyncio.TimerHandle | None = None

    def soon(self) -> None:
        """Trim TRIM_DELAY_S from now (call on the event loop)."""
        if self._libc is None or self._pending is not None:
            return
        self._pending = asyncio.get_running_loop().call_later(TRIM_DELAY_S, self._trim)

    def _trim(self) -> None:
        self._pending = None
        if self._libc is not None:
            self._libc.malloc_trim(0)
