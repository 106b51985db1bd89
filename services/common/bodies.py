"""Request bodies: JSON validated into models, with clear 400, 415 and 422 errors.

Bodies are parsed with ``robocloud.bounded_json``, whose nesting bound is checked without
recursion: a 100,000-deep document is 400 ``json_too_deep`` (``COMMON_ERRORS``), never a
crash. Not valid JSON is 400 ``invalid_json``.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any, TypeVar

import anyio
from fastapi import Query, Request
from pydantic import BaseModel, ValidationError

from robocloud import bounded_json
from robocloud.client import MAX_WAIT_S
from services.common.errors import PayloadTooLarge, Unprocessable, UnsupportedMediaType

M = TypeVar("M", bound=BaseModel)

INLINE_JSON_BYTES = 64 * 1024
"""A JSON body larger than this is parsed and validated on a worker thread: 16 MiB of nested
arrays took 8 s of the event loop, every other request of the service waiting."""
SMALL_JSON_BODY = 64 * 1024
"""The body limit of routes whose JSON is a few fields (``/v1/whoami``, the faucet)."""


def field_errors(exc: ValidationError, prefix: str = "body") -> list[dict[str, Any]]:
    """Pydantic's errors as ``{"field": "body.a.0.b", "message": ...}``, naming each field."""
    return [
        {
            "field": ".".join(str(part) for part in (prefix, *error["loc"])),
            "message": error["msg"],
            "type": error["type"],
        }
        for error in exc.errors()
    ]


def wait_parameter(description: str) -> Any:
    """A long poll's ``wait_s`` query parameter (``changes.long_poll``): from 0, an answer at
    once, to ``MAX_WAIT_S``; out of bounds, a 422 naming ``query.wait_s``."""
    return Query(default=0, ge=0, le=MAX_WAIT_S, description=description)


def media_type(request: Request) -> str:
    return request.headers.get("content-type", "").split(";", 1)[0].strip().lower()


async def read_json(
    request: Request,
    model: type[M],
    *,
    optional: bool = False,
    max_depth: int = bounded_json.MAX_DEPTH,
    max_bytes: int | None = None,
) -> M | None:
    """Read and validate a JSON body; ``None`` for an empty body when ``optional``.

    Raises ``JsonError``/``JsonDepthError`` (answered 400 by ``COMMON_ERRORS``) for a body
    that is not JSON or nests deeper than ``max_depth``, and 413 for one over ``max_bytes``
    (:func:`bounded_body`).
    """
    raw = await request.body() if max_bytes is None else await bounded_body(request, max_bytes)
    if not raw and optional:
        return None
    if media_type(request) != "application/json":
        raise UnsupportedMediaType(
            "the body must be application/json",
            details={"header": "Content-Type", "received": request.headers.get("content-type")},
        )
    if len(raw) > INLINE_JSON_BYTES:
        return await anyio.to_thread.run_sync(_validated, raw, model, max_depth)
    return _validated(raw, model, max_depth)


async def bounded_body(request: Request, max_bytes: int) -> bytes:
    """The body, refused with 413 once it is past ``max_bytes`` (by its ``Content-Length``
    before a byte is read). For a JSON body of a few fields on a route whose uploads are
    much larger: ``/v1/ingest`` takes a bag of up to 16 GiB, or ``{"cid"}``, and a JSON body
    as large as a bag was read whole into memory."""
    declared = request.headers.get("content-length", "")
    if declared.isdigit() and int(declared) > max_bytes:
        raise PayloadTooLarge(
            f"Content-Length {declared} exceeds the limit of {max_bytes} bytes of a JSON body",
            details={"header": "Content-Length", "limit": max_bytes},
        )
    return b"".join([chunk async for chunk in bounded_stream(request, max_bytes, "a JSON body")])


async def bounded_stream(request: Request, max_bytes: int, what: str) -> AsyncIterator[bytes]:
    """The body's chunks as they arrive; 413 once more than ``max_bytes`` came, before the
    chunk past them is kept ("``what`` holds at most ..." bytes)."""
    received = 0
    async for chunk in request.stream():
        received += len(chunk)
        if received > max_bytes:
            raise PayloadTooLarge(
                f"{what} holds at most {max_bytes} bytes here", details={"limit": max_bytes}
            )
        yield chunk


def _validated(raw: bytes, model: type[M], max_depth: int) -> M:
    document = bounded_json.loads(raw, max_depth=max_depth)
    try:
        return model.model_validate(document)
    except ValidationError as exc:
        errors = field_errors(exc)
        raise Unprocessable(
            f"invalid body: {errors[0]['field']}: {errors[0]['message']}",
            details={"errors": errors},
        ) from exc


def json_body(model: type[M], *, max_bytes: int | None = None) -> Callable[[Request], Awaitable[M]]:
    """A dependency giving the validated body; use as ``body: M = Depends(json_body(M))``.
    ``max_bytes`` bounds it below the route's body limit (:func:`bounded_body`)."""

    async def dependency(request: Request) -> M:
        body = await read_json(request, model, max_bytes=max_bytes)
        assert body is not None
        return body

    return dependency
