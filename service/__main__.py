"""`python -m crestereo_pp.service`: the service under uvicorn, with the server limits it is sized for.

    python -m crestereo_pp.service [--host 127.0.0.1] [--port 8000]

The address defaults come from UVICORN_HOST / UVICORN_PORT (the container sets 0.0.0.0:8000),
else loopback:8000. The limits below are uvicorn's own; service/README.md ("Server limits")
says what each bounds and what uvicorn cannot bound.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
from typing import TypedDict

import uvicorn

from crestereo_pp.service.batching.daemon_thread import any_busy
from crestereo_pp.service.settings import Settings
from crestereo_pp.service.uploads.budgets import largest_stream_image
from crestereo_pp.service.uploads.memory import limit_malloc_arenas
from crestereo_pp.service.uploads.protocols import BoundedH11Protocol, BoundedWebSocketProtocol


class ServerLimits(TypedDict):
    """uvicorn.run's keywords for the server limits (typed, so that they are checked against it)."""

    limit_concurrency: int
    timeout_keep_alive: int
    h11_max_incomplete_event_size: int
    ws_per_message_deflate: bool


SERVER_LIMITS: ServerLimits = {
    # Open connections (idle and slow ones included) before uvicorn answers 503 (text) itself:
    # far above what the app serves at once (CRESTEREO_MAX_REQUESTS, JSON 503 `overloaded`
    # beyond it; CRESTEREO_MAX_STREAMS WebSockets, refused at the handshake with JSON 503 beyond
    # it), so that a thousand idle connections leave room for the probes. Each needs a file
    # descriptor: serve() raises the soft RLIMIT_NOFILE to fit (FILE_DESCRIPTORS_BESIDE
    # connections). Beyond it, connection floods are a reverse proxy's job.
    "limit_concurrency": 2048,
    # Seconds an idle keep-alive connection is held open.
    "timeout_keep_alive": 5,
    # Bytes of an unparsed request head before uvicorn answers 400 (text) itself: up to this, the
    # head reaches the app, which answers 431 (JSON) over 16 KiB. The trade with limit_concurrency:
    # in the worst case, every connection sending a head just under it, uvicorn holds
    # limit_concurrency x 512 KiB = 1 GiB; a larger cap would need fewer connections.
    "h11_max_incomplete_event_size": 512 * 1024,
    # WebSocket messages uncompressed: with permessage-deflate, a few KiB on the wire could
    # inflate to a whole message of zeros. A message's size (`ws_max_size`, from the settings)
    # then bounds what a client must send, byte for byte.
    "ws_per_message_deflate": False,
}
FILE_DESCRIPTORS_BESIDE = 256
"""File descriptors the server needs besides its connections' (the listening socket, the decoder
processes' pipes, logs, the models' and libraries' files), for the soft RLIMIT_NOFILE."""
SHUTDOWN_MARGIN_S = 5
"""After SIGTERM the service's drain (CRESTEREO_DRAIN_TIMEOUT_S) answers every admitted request;
uvicorn cancels whatever still runs this long after it (a client that never reads its answer)."""


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m crestereo_pp.service", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--host", default=os.environ.get("UVICORN_HOST", "127.0.0.1"))
    parser.add_argument("--port", type=int, default=int(os.environ.get("UVICORN_PORT", "8000")))
    args = parser.parse_args(argv)
    serve(args.host, args.port)


def serve(host: str, port: int) -> None:
    """Serve the app under uvicorn on host:port until SIGTERM or SIGINT (then drain)."""
    settings = Settings.from_env()
    limit_malloc_arenas()
    needed = SERVER_LIMITS["limit_concurrency"] + FILE_DESCRIPTORS_BESIDE
    allowed = raise_open_files_limit(needed)
    if allowed is not None and allowed < needed:
        logging.getLogger(__name__).warning(
            "the open files limit (ulimit -n) is below %d: past it, new connections fail before "
            "uvicorn's limit_concurrency answers 503",
            needed,
        )
    shutdown_s = math.ceil(settings.drain_timeout_s) + SHUTDOWN_MARGIN_S
    uvicorn.run(
        "crestereo_pp.service.api.app:create_app",
        factory=True,
        host=host,
        port=port,
        timeout_graceful_shutdown=shutdown_s,
        # h11 and asyncio, named: uvicorn picks httptools and uvloop wherever they are installed
        # (Ray Serve installs both), and the head-size limit above is h11's (httptools answers a
        # long request line with its own text 400 before the app can answer its JSON 414). Both
        # protocols are uvicorn's, bounding the pieces a body or message may come in
        # (`uploads.protocols`).
        http=BoundedH11Protocol,
        loop="asyncio",
        # websockets-sansio, named too: it reads no further than one whole message ahead of the app.
        ws=BoundedWebSocketProtocol,
        # Bytes of one WebSocket message (`/disparity/stream`, the one WebSocket route: one image
        # file) before uvicorn closes the connection (1009), unread: CRESTEREO_MAX_STREAM_IMAGE_BYTES,
        # or the largest file an image within the pixel limit makes where smaller. uvicorn reads a
        # stream's next message whole before the app takes it, outside the streams' byte budget.
        ws_max_size=largest_stream_image(
            settings.max_image_pixels, settings.max_body_bytes, settings.max_stream_image_bytes
        ),
        **SERVER_LIMITS,
    )
    # Only reached where SIGTERM does not end the process (uvicorn re-raises it; PID 1 ignores
    # it). A batch abandoned at the drain timeout may still compute: leave without running
    # torch's static destructors under it, which would abort the process.
    if any_busy():
        logging.shutdown()
        os._exit(0)


def raise_open_files_limit(needed: int) -> int | None:
    """Raise this process's soft RLIMIT_NOFILE to `needed` file descriptors where it is lower, as far as
    the hard limit allows; never fails (nothing changes where it cannot). Returns the soft limit now
    (sys.maxsize where unlimited), or None where it cannot be read."""
    try:
        import resource
    except ImportError:  # not POSIX
        return None
    try:
        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    except (OSError, ValueError):
        return None
    if soft == resource.RLIM_INFINITY:
        return sys.maxsize
    if soft >= needed:
        return soft
    target = needed if hard == resource.RLIM_INFINITY else min(needed, hard)
    if target <= soft:
        return soft
    try:
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
    except (OSError, ValueError):
        return soft
    return target


if __name__ == "__main__":
    main()
