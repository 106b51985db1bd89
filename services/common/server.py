"""The HTTP/1.1 server protocol: uvicorn's h11 protocol, bounding each request head as it arrives.

uvicorn's default parser (httptools) has no bound on a request head: it buffers a header
field until it ends, so a 200 MiB header took 47 s and 400 MiB of memory, and a 64 MiB one
stalled every other request. Here the bytes of each request head are counted before the
parser sees them: a request line longer than ``max_request_line_bytes`` is answered 414 and a
head (request line and header fields) longer than ``max_header_bytes`` 431, both as soon as
the bytes that break the limit arrive, and the connection is closed without reading the rest.
A head must also be complete within ``header_timeout_s`` of its first byte (408), so that
connections dribbling a byte at a time cannot be held open until the process runs out of
file descriptors: uvicorn times out only idle kept-alive connections.
A body must keep arriving, and an answer must be taken: a client that sends nothing of its
body for ``body_timeout_s`` (while the service is ready to read it) is answered 408, as
nginx's ``client_body_timeout`` does, and one that reads nothing of the answer for
``send_timeout_s`` (its write buffer stays above the high-water mark) is dropped, what is
buffered for it discarded, as nginx's ``send_timeout`` does; either way the connection is
closed and the route sees its client gone. Before, an upload that stopped half way held its
staging file and its connection for ever, and a client that asked for a large stream and never
read held the stream open with the read-ahead behind it: a hundred such connections held
430 MiB of the cas.
h11 buffers at most one head, and its own bound (``h11_max_incomplete_event_size``) is set to
the same limit as a backstop for pipelined requests, whose bytes may arrive together with an
earlier request's body.
A request h11 cannot frame (a bad or doubled ``Content-Length``, a transfer coding other than
chunked, a bad chunk size, no ``Host``, a malformed header line) is answered in the error model
too, ``bad_http_request`` with h11's reason and its status (400; 501 for a transfer coding it
does not implement, as RFC 9112 section 6.1 asks), and the connection closed: uvicorn answered
a plain-text "Invalid HTTP request received." that said neither what was wrong nor which
request id to quote.
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
import uuid
from dataclasses import dataclass
from http import HTTPStatus
from typing import Any, ClassVar

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from services.common.errors import error_body
from services.common.logs import request_id_var
from services.common.middleware import REQUEST_ID_SCOPE_KEY, SERVER_ANSWER_SCOPE_KEY

log = logging.getLogger("robocloud.http")

_BLANK_LINE = re.compile(rb"\n\r?\n")
"""The end of a head as h11 finds it (a CRLF or bare LF line, then an empty one)."""
_MAX_REASON_CHARS = 200
"""How much of h11's reason a ``bad_http_request`` quotes: it may hold a whole header line."""
_UNPRINTABLE = re.compile(r"[^\x20-\x7e]")


@dataclass(frozen=True)
class Refusal:
    """Why the server itself refuses a request (its head, or a body that stopped coming): the
    status and the JSON error that says so."""

    status: int
    code: str
    message: str
    details: dict[str, float]


class HeadMeter:
    """Counts the bytes of one request head as they arrive, and says when one is too long.

    ``feed`` sees each received chunk; it looks only at new bytes (plus two carried over, for
    a blank line split between chunks), so a head sent a byte at a time costs linear time.
    """

    def __init__(self, max_request_line_bytes: int, max_header_bytes: int) -> None:
        self.max_request_line_bytes = max_request_line_bytes
        self.max_header_bytes = max_header_bytes
        self.start()

    def start(self) -> None:
        """Begin counting a new head (at connection start and after each request)."""
        self.counting = True
        self._line_open = True
        self._line_bytes = 0
        self._head_bytes = 0
        self._tail = b""

    def feed(self, data: bytes) -> Refusal | None:
        """Count ``data``; a refusal once the head breaks a limit, else None."""
        if not self.counting or not data:
            return None
        if self._line_open:
            line_end = data.find(b"\n")
            self._line_bytes += len(data) if line_end == -1 else line_end
            self._line_open = line_end == -1
            if self._line_bytes > self.max_request_line_bytes:
                return Refusal(
                    414,
                    "request_line_too_long",
                    f"the request line exceeds {self.max_request_line_bytes} bytes",
                    {"limit": self.max_request_line_bytes},
                )
        window = self._tail + data
        end = _BLANK_LINE.search(window)
        if end is None:
            self._head_bytes += len(data)
            self._tail = window[-2:]
        else:
            self._head_bytes += end.end() - len(self._tail)
            self.counting = False
        if self._head_bytes > self.max_header_bytes:
            return Refusal(
                431,
                "headers_too_large",
                f"the request head (request line and header fields) exceeds "
                f"{self.max_header_bytes} bytes",
                {"limit": self.max_header_bytes},
            )
        return None


class _ErrorKeepingConnection(h11.Connection):
    """h11's connection, keeping the protocol error it raised and whether the request's body
    was arriving then: uvicorn catches the error and keeps neither."""

    error: h11.RemoteProtocolError | None = None
    error_in_body = False

    def next_event(self) -> h11.Event | type[h11.NEED_DATA] | type[h11.PAUSED]:
        in_body = self.their_state is h11.SEND_BODY
        try:
            return super().next_event()
        except h11.RemoteProtocolError as exc:
            self.error, self.error_in_body = exc, in_body
            raise


def _quoted_reason(exc: h11.RemoteProtocolError | None, fallback: str) -> str:
    """h11's reason for refusing a request, printable ASCII and bounded: it quotes the
    client's own bytes, which go back in the answer and into the log."""
    reason = _UNPRINTABLE.sub("?", str(exc) if exc is not None else fallback)
    if len(reason) > _MAX_REASON_CHARS:
        reason = reason[: _MAX_REASON_CHARS - 3] + "..."
    return reason


class BoundedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with :class:`HeadMeter` in front of the parser.

    Use :func:`bounded_protocol` to get a subclass carrying a service's limits: uvicorn builds
    one protocol object per connection from the class alone.
    """

    max_request_line_bytes: ClassVar[int] = 8 * 1024
    max_header_bytes: ClassVar[int] = 64 * 1024
    header_timeout_s: ClassVar[float] = 30.0
    body_timeout_s: ClassVar[float] = 30.0
    send_timeout_s: ClassVar[float] = 30.0

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._framing = _ErrorKeepingConnection(
            h11.SERVER, self.config.h11_max_incomplete_event_size or self.max_header_bytes
        )
        self.conn = self._framing
        self._head = HeadMeter(self.max_request_line_bytes, self.max_header_bytes)
        self._head_deadline: asyncio.TimerHandle | None = None
        self._send_deadline: asyncio.TimerHandle | None = None
        self._body_deadline: asyncio.TimerHandle | None = None
        self._body_seen = 0.0
        self._refused = False

    def data_received(self, data: bytes) -> None:
        if self._refused:
            return
        if self.conn.their_state is h11.IDLE:
            refusal = None
            if not self._head.counting:
                # A new request: count what h11 kept of it from earlier reads, then the rest.
                self._head.start()
                refusal = self._head.feed(self.conn.trailing_data[0])
            refusal = refusal or self._head.feed(data)
            if refusal is not None:
                self._refuse(refusal)
                return
            if self._head.counting and self._head_deadline is None:
                self._head_deadline = self.loop.call_later(self.header_timeout_s, self._too_slow)
            elif not self._head.counting:
                self._head_deadline = _cancelled(self._head_deadline)
        super().data_received(data)
        self._watch_body()

    def connection_lost(self, exc: Exception | None) -> None:
        self._head_deadline = _cancelled(self._head_deadline)
        self._send_deadline = _cancelled(self._send_deadline)
        self._body_deadline = _cancelled(self._body_deadline)
        super().connection_lost(exc)

    def _watch_body(self) -> None:
        """While a request body is arriving, each piece has ``body_timeout_s`` to come."""
        if self.conn.their_state is not h11.SEND_BODY:
            self._body_deadline = _cancelled(self._body_deadline)
            return
        self._body_seen = self.loop.time()
        if self._body_deadline is None:
            self._body_deadline = self.loop.call_later(self.body_timeout_s, self._body_overdue)

    def _body_overdue(self) -> None:
        self._body_deadline = None
        if self.conn.their_state is not h11.SEND_BODY:
            return
        now = self.loop.time()
        if self.flow.read_paused:
            # The service stopped reading (the route is behind), not the client sending.
            self._body_seen = now
        idle = now - self._body_seen
        if idle < self.body_timeout_s:
            self._body_deadline = self.loop.call_later(
                self.body_timeout_s - idle, self._body_overdue
            )
            return
        if self.cycle is None or self.cycle.response_started:
            self._drop("client stopped sending its body", {"body_timeout_s": self.body_timeout_s})
            return
        # The route waits for the rest of the body: it gets its client's disconnection.
        self.scope[SERVER_ANSWER_SCOPE_KEY] = 408  # type: ignore[literal-required]
        self.cycle.disconnected = True
        self.cycle.message_event.set()
        self._refuse(
            Refusal(
                408,
                "body_timeout",
                f"the request body stopped arriving for {self.body_timeout_s:g} s",
                {"limit_s": self.body_timeout_s},
            ),
            self._request_id(),
            self._path(),
        )

    def send_400_response(self, msg: str) -> None:
        """h11 refused the request's framing (uvicorn calls this with its own fixed ``msg``):
        answer ``bad_http_request`` with h11's reason and close. If the body was arriving,
        the route sees its client gone; if its answer had started, the connection is dropped,
        since nothing can be answered in the middle of an answer."""
        error, in_body = self._framing.error, self._framing.error_in_body
        reason = _quoted_reason(error, msg)
        if in_body and self.cycle is not None and self.cycle.response_started:
            self._drop(f"badly framed request body ({reason})", {})
            return
        status = error.error_status_hint if error is not None else 400
        refusal = Refusal(
            status, "bad_http_request", f"the request is not valid HTTP/1.1: {reason}", {}
        )
        if not in_body or self.cycle is None:
            self._refuse(refusal)
            return
        self.scope[SERVER_ANSWER_SCOPE_KEY] = status  # type: ignore[literal-required]
        self.cycle.disconnected = True
        self.cycle.message_event.set()
        self._refuse(refusal, self._request_id(), self._path())

    def pause_writing(self) -> None:
        """The client is not taking the answer as fast as it is written: it has
        ``send_timeout_s`` to take some of it."""
        super().pause_writing()
        if self._send_deadline is None:
            self._send_deadline = self.loop.call_later(self.send_timeout_s, self._not_reading)

    def resume_writing(self) -> None:
        self._send_deadline = _cancelled(self._send_deadline)
        super().resume_writing()

    def _not_reading(self) -> None:
        self._send_deadline = None
        self._drop("client stopped reading", {"send_timeout_s": self.send_timeout_s})

    def _drop(self, why: str, limit: dict[str, float]) -> None:
        """Drop the connection and what is buffered for it. The route sees a disconnected
        client: an upload discards what it staged, a stream stops and gives back its turn."""
        token = request_id_var.set(self._request_id() or "-")
        try:
            log.warning(
                f"{why}; connection dropped",
                extra={"client": self.client, "path": self._path(), **limit},
            )
        finally:
            request_id_var.reset(token)
        self.transport.abort()

    def _request_id(self) -> str | None:
        """The id the request layers gave the connection's current request, once they have."""
        request_id = getattr(self, "scope", {}).get(REQUEST_ID_SCOPE_KEY)
        return request_id if isinstance(request_id, str) else None

    def _path(self) -> str | None:
        """The current request's path, once its head arrived."""
        path = getattr(self, "scope", {}).get("path")
        return path if isinstance(path, str) else None

    def _too_slow(self) -> None:
        self._head_deadline = None
        if self._head.counting and self.conn.their_state is h11.IDLE and not self._refused:
            self._refuse(
                Refusal(
                    408,
                    "header_timeout",
                    f"the request head did not arrive within {self.header_timeout_s:g} s",
                    {"limit_s": self.header_timeout_s},
                )
            )

    def _refuse(
        self, refusal: Refusal, request_id: str | None = None, path: str | None = None
    ) -> None:
        """Answer in the error model and close without reading the rest of the request (its
        id and path, when its head was read: a head refused has neither)."""
        self._refused = True
        self._head_deadline = _cancelled(self._head_deadline)
        request_id = request_id or uuid.uuid4().hex
        token = request_id_var.set(request_id)
        try:
            log.warning(
                "request refused",
                extra={
                    "status": refusal.status,
                    "code": refusal.code,
                    "client": self.client,
                    "path": path,
                },
            )
        finally:
            request_id_var.reset(token)
        error = error_body(refusal.code, refusal.message, refusal.details, request_id)
        body = json.dumps(error).encode()
        head = (
            f"HTTP/1.1 {refusal.status} {HTTPStatus(refusal.status).phrase}\r\n"
            "content-type: application/json\r\n"
            f"content-length: {len(body)}\r\n"
            "connection: close\r\n"
            f"x-request-id: {request_id}\r\n\r\n"
        ).encode()
        self.transport.write(head + body)
        self.transport.close()


def _cancelled(timer: asyncio.TimerHandle | None) -> asyncio.TimerHandle | None:
    """Cancel ``timer`` if there is one; None, what the attribute that held it holds next."""
    if timer is not None:
        timer.cancel()
    return None


def bounded_protocol(
    max_request_line_bytes: int,
    max_header_bytes: int,
    header_timeout_s: float,
    body_timeout_s: float,
    send_timeout_s: float,
) -> type[H11Protocol]:
    """The protocol class for uvicorn's ``http=`` with these limits."""
    return type(
        "BoundedH11Protocol",
        (BoundedH11Protocol,),
        {
            "max_request_line_bytes": max_request_line_bytes,
            "max_header_bytes": max_header_bytes,
            "header_timeout_s": header_timeout_s,
            "body_timeout_s": body_timeout_s,
            "send_timeout_s": send_timeout_s,
        },
    )
