"""The checks every query string gets, on `POST /disparity` and `/disparity/stream` alike: its
length (`query_too_long`, before anything else reads it; the middleware answers 414 over it) and
options given more than once (`repeated_option`), both linear in its length."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable

MAX_QUERY_BYTES = 4 * 1024
"""Longest query string the app accepts: 414 beyond (every option of `/disparity` together fits
in a few hundred bytes), so no later check of the query costs more than this much input."""


def query_too_long(query_string: bytes) -> str | None:
    """Why a query string is refused for its length (over MAX_QUERY_BYTES), else None."""
    if len(query_string) <= MAX_QUERY_BYTES:
        return None
    return f"query string of {len(query_string)} bytes; the limit is {MAX_QUERY_BYTES}"


def repeated_option(items: Iterable[tuple[str, str]]) -> str | None:
    """What is wrong with a query that gives an option more than once (`?model=lite&model=full` is
    ambiguous: refused rather than silently taking one), else None. One pass over the query, linear
    in its length (which `query_too_long` bounds)."""
    counts = Counter(name for name, _ in items)
    repeated = min((name for name, count in counts.items() if count > 1), default=None)
    return None if repeated is None else f"query.{repeated}: given more than once"
