"""Structured logs: one JSON object a line, carrying the service name and the request id.

The request id lives in a context variable set by the request middleware, so every log line
written while serving a request (domain code included) carries it without passing it around.

A line is formatted where it is logged (the request id is known there) and written to stderr
by a thread of its own: a write to a stderr that takes nothing (a terminal paused with
Ctrl-S, a supervisor or a pipe nobody reads) blocked the event loop, and every route of the
service with it. Past :data:`MAX_QUEUED_LINES` waiting lines are dropped and counted, and the
count is logged once stderr takes lines again.
"""

from __future__ import annotations

import atexit
import json
import logging
import queue
import sys
import threading
import time
from contextvars import ContextVar
from typing import Any, TextIO

request_id_var: ContextVar[str] = ContextVar("request_id", default="-")

_RESERVED = set(logging.LogRecord("", 0, "", 0, "", None, None).__dict__) | {
    "message",
    "color_message",  # uvicorn duplicates msg with ANSI colours for its own formatter
}


class JsonFormatter(logging.Formatter):
    def __init__(self, service: str) -> None:
        super().__init__()
        self.service = service

    def format(self, record: logging.LogRecord) -> str:
        entry: dict[str, Any] = {
            "ts": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
            + f".{int(record.msecs):03d}Z",
            "level": record.levelname.lower(),
            "service": self.service,
            "logger": record.name,
            "request_id": request_id_var.get(),
            "msg": record.getMessage(),
        }
        for key, value in record.__dict__.items():
            if key not in _RESERVED and not key.startswith("_"):
                entry[key] = value
        if record.exc_info:
            entry["exc"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str)


MAX_QUEUED_LINES = 10_000
"""Lines held while stderr takes none; past them lines are dropped, never waited for."""
STOP_WAIT_S = 5.0
"""How long an exiting process waits for stderr to take what is queued."""


class _LineWriter:
    """A thread writing queued lines to ``stream`` in order; ``None`` stops it.

    Not ``logging.handlers.QueueListener``: its ``stop`` puts its sentinel without waiting
    (``queue.Full`` on a full queue) and then joins the thread without a bound, so a process
    whose stderr takes nothing could not exit."""

    def __init__(self, stream: TextIO) -> None:
        self.lines: queue.Queue[str | None] = queue.Queue(MAX_QUEUED_LINES)
        self.stream = stream
        self.thread = threading.Thread(target=self._write, name="log writer", daemon=True)
        self.thread.start()

    def _write(self) -> None:
        while (line := self.lines.get()) is not None:
            try:
                self.stream.write(line + "\n")
                self.stream.flush()
            except (OSError, ValueError):  # stderr closed: the lines have nowhere to go
                pass

    def stop(self) -> None:
        """Let the thread write what is queued, within :data:`STOP_WAIT_S`."""
        try:
            self.lines.put(None, timeout=STOP_WAIT_S)
        except queue.Full:
            return
        self.thread.join(STOP_WAIT_S)


class _QueuedLines(logging.Handler):
    """Formats each line where it is logged and queues it for the writer, dropping it
    (counted) when :data:`MAX_QUEUED_LINES` already wait."""

    def __init__(self, writer: _LineWriter, formatter: logging.Formatter) -> None:
        super().__init__()
        self.writer = writer
        self.setFormatter(formatter)
        self.dropped = 0
        """Lines dropped since the last one queued; the handler's lock guards it."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            line = self.format(record)
        except Exception:
            self.handleError(record)
            return
        try:
            if self.dropped:
                self.writer.lines.put_nowait(self.format(self._dropped_notice()))
                self.dropped = 0
            self.writer.lines.put_nowait(line)
        except queue.Full:
            self.dropped += 1

    def _dropped_notice(self) -> logging.LogRecord:
        return logging.LogRecord(
            __name__,
            logging.WARNING,
            __file__,
            0,
            "%d log lines dropped: stderr took none while %d waited",
            (self.dropped, MAX_QUEUED_LINES),
            None,
        )

    def stop(self) -> None:
        """Queue the count of lines dropped, if any, and stop the writer once it wrote
        what is queued (within :data:`STOP_WAIT_S`)."""
        self.acquire()
        try:
            if self.dropped:
                notice = self.format(self._dropped_notice())
                self.writer.lines.put(notice, timeout=STOP_WAIT_S)
                self.dropped = 0
        except queue.Full:
            return
        finally:
            self.release()
        self.writer.stop()


_handler: _QueuedLines | None = None
"""Where every logger's lines go once logging is configured."""


def stop_logging() -> None:
    """Write the lines still queued and stop the writer thread: at exit, and before a
    reader of stderr (a test) looks."""
    global _handler
    if _handler is not None:
        _handler.stop()
        _handler = None


atexit.register(stop_logging)


def configure_logging(service: str, level: str = "INFO") -> None:
    """Send every logger, uvicorn's included, through the JSON formatter to stderr, written by
    a thread of its own."""
    global _handler
    stop_logging()
    handler = _handler = _QueuedLines(_LineWriter(sys.stderr), JsonFormatter(service))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
    for name in ("uvicorn", "uvicorn.error"):
        logging.getLogger(name).handlers[:] = []
        logging.getLogger(name).propagate = True
    logging.getLogger("uvicorn.access").disabled = True
    # httpx writes a line at INFO for every request a service makes, with no request id when a
    # background task makes it: idle under `make up`, the ledger's role granter and the
    # storage node's knowledge follower wrote several a second, and the peer's access log
    # already records each request. They are shown at DEBUG.
    outgoing = logging.NOTSET if root.level <= logging.DEBUG else logging.WARNING
    for name in ("httpx", "httpcore"):
        logging.getLogger(name).setLevel(outgoing)
