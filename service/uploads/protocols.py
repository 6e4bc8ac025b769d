"""uvicorn's HTTP/1.1 (h11) and WebSocket (websockets-sansio) protocols, bounding the pieces a
request body or a WebSocket message may come in.

uvicorn parses each piece (an HTTP chunk, a WebSocket fragment) in Python on the event loop, so a
body sent as millions of one-byte chunks (or a message as millions of one-byte fragments) costs
the server some 8 µs per piece, for 6 bytes on the wire: a few such uploads held the loop for
seconds at a time, the probes included. Here a body or message may come in at most
`MIN_PIECES_ALLOWED` pieces, plus one for every `MEAN_PIECE_BYTES` bytes it has brought: any
client's chunking passes (pieces of 256 bytes or more on average, or a thousand of any size),
while what a flood of pieces costs the server stays near what its bytes cost in large ones. Past
that the connection is closed: an HTTP request is answered 400 `too_many_pieces` (JSON), a stream
is sent that error as a text message, then closed with 1008.

uvicorn's other refusals of malformed HTTP (a negative Content-Length, a request line it cannot
parse) are answered here in JSON too (400 `malformed_request`), as the app answers every error.
"""

from __future__ import annotations

import asyncio
import json
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol
from websockets.frames import Frame

MIN_PIECES_ALLOWED = 1024
"""Pieces any body or message may come in, however small."""
MEAN_PIECE_BYTES = 256
"""Past MIN_PIECES_ALLOWED, one more piece for every this many bytes brought."""
LINGER_S = 2.0
"""After a refusal, how long the rest of what the client sends is read and dropped before the
connection is closed (`LingeringClose`)."""
POLICY_VIOLATION = 1008
MAX_CLOSE_REASON = 120
"""Characters of a close frame's reason (a control frame holds at most 125 bytes)."""


def too_many_pieces(pieces: int, size: int) -> bool:
    """Whether `pieces` pieces bringing `size` bytes in all are more than a body may come in."""
    return pieces > MIN_PIECES_ALLOWED + size // MEAN_PIECE_BYTES


def pieces_refusal(pieces: int, size: int) -> str:
    """Why a body or message of `pieces` pieces and `size` bytes so far was refused, for the client."""
    return (
        f"{pieces} pieces bringing {size} bytes: a body or message may come in {MIN_PIECES_ALLOWED} pieces, "
        f"and one more for every {MEAN_PIECE_BYTES} bytes; send it in larger chunks or fragments"
    )


class LingeringClose:
    """A lingering close, as web servers make one: once a refusal is written, the rest of what the
    client sends is read and dropped, unparsed, and the connection closed LINGER_S later (or when
    the client closes it). Closed at once, unread data would make the kernel reset the connection,
    and a client still sending could lose the refusal before reading it."""

    transport: asyncio.Transport
    loop: asyncio.AbstractEventLoop
    lingering = False

    def data_received(self, data: bytes) -> None:
        if not self.lingering:
            super().data_received(data)  # type: ignore[misc]

    def linger(self) -> None:
        """Close after LINGER_S, dropping what arrives meanwhile; the refusal is written already."""
        self.lingering = True
        if self.transport.can_write_eof():
            self.transport.write_eof()
        self.loop.call_later(LINGER_S, self.transport.close)


MALFORMED = "not a valid HTTP/1.1 request: its request line, a header or the framing of its body is malformed"


class PieceCountingConnection(h11.Connection):
    """h11's server side, which counts the pieces (Data events) of each request's body and raises
    `h11.RemoteProtocolError` (uvicorn then answers 400 and closes) past `too_many_pieces`;
    `refusal` then says why."""

    def __init__(self, max_incomplete_event_size: int | None) -> None:
        if max_incomplete_event_size is None:  # h11's default
            super().__init__(h11.SERVER)
        else:
            super().__init__(h11.SERVER, max_incomplete_event_size=max_incomplete_event_size)
        self.pieces = 0
        self.size = 0
        self.refusal: str | None = None

    def next_event(self) -> Any:
        event = super().next_event()
        if isinstance(event, h11.Request):
            self.pieces = self.size = 0
        elif isinstance(event, h11.Data):
            self.pieces += 1
            self.size += len(event.data)
            if too_many_pieces(self.pieces, self.size):
                self.refusal = pieces_refusal(self.pieces, self.size)
                raise h11.RemoteProtocolError(self.refusal, error_status_hint=400)
        return event


class BoundedH11Protocol(LingeringClose, H11Protocol):
    """uvicorn's h11 protocol with `PieceCountingConnection`, answering its 400s in JSON, with a
    lingering close."""

    conn: PieceCountingConnection

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.conn = PieceCountingConnection(self.config.h11_max_incomplete_event_size)

    def send_400_response(self, msg: str) -> None:
        if self.conn.our_state not in (h11.IDLE, h11.SEND_RESPONSE):  # answered already: the rest goes unread
            self.transport.close()
            return
        refusal = self.conn.refusal
        code, message = ("too_many_pieces", refusal) if refusal else ("malformed_request", MALFORMED)
        body = json.dumps({"error": {"code": code, "message": message}}).encode()
        headers = [
            (b"content-type", b"application/json"),
            (b"content-length", str(len(body)).encode()),
            (b"connection", b"close"),
        ]
        response = h11.Response(status_code=400, headers=headers, reason=b"Bad Request")
        for event in (response, h11.Data(data=body), h11.EndOfMessage()):
            self.transport.write(self.conn.send(event) or b"")
        self.linger()


class BoundedWebSocketProtocol(LingeringClose, WebSocketsSansIOProtocol):
    """uvicorn's websockets-sansio protocol, which closes a stream (1008, with a lingering close)
    whose message comes in more fragments than `too_many_pieces` allows."""

    pieces = 0
    size = 0

    def handle_text(self, event: Frame) -> None:
        self.pieces, self.size = 1, len(event.data)
        super().handle_text(event)

    def handle_bytes(self, event: Frame) -> None:
        self.pieces, self.size = 1, len(event.data)
        super().handle_bytes(event)

    def handle_cont(self, event: Frame) -> None:
        if self.close_sent:
            return  # the rest of a refused message, parsed in the same read
        self.pieces += 1
        self.size += len(event.data)
        if too_many_pieces(self.pieces, self.size):
            self.frames = []
            refusal = pieces_refusal(self.pieces, self.size)  # said as the stream route says its errors
            self.conn.send_text(json.dumps({"error": {"code": "too_many_pieces", "message": refusal}}).encode())
            self.conn.fail(POLICY_VIOLATION, refusal[:MAX_CLOSE_REASON])
            self.queue.put_nowait({"type": "websocket.disconnect", "code": POLICY_VIOLATION, "reason": refusal})
            self.transport.write(b"".join(self.conn.data_to_send()))
            self.close_sent = True
            self.linger()
            return
        super().handle_cont(event)
