"""The trustless gateway: ``GET|HEAD /ipfs/{cid}`` as file bytes, one raw block, or a CAR.

Follows the IPFS trustless gateway and path gateway specs for what a verifying client needs:
``format`` or ``Accept`` picks the response type, ``dag-scope`` the CAR's extent, ``Range``
a byte range of a file, ``If-None-Match`` a 304, and ``Cache-Control: only-if-cached`` an
answer from the local store alone (412 on a miss), which is what peers ask each other.
"""

from __future__ import annotations

from typing import Annotated

import anyio
from fastapi import APIRouter, Query, Request
from fastapi.responses import Response, StreamingResponse

from robocloud.cid import CID, parse_cid
from services.cas.ranges import byte_range
from services.cas.store import BlockUnavailable, ContentStore
from services.cas.streams import threaded_stream
from services.common.errors import BadRequest, ServiceError

RAW_MEDIA_TYPE = "application/vnd.ipld.raw"
CAR_MEDIA_TYPE = "application/vnd.ipld.car"
IMMUTABLE = "public, max-age=29030400, immutable"
FORMATS = {"raw": RAW_MEDIA_TYPE, "car": CAR_MEDIA_TYPE}

router = APIRouter(tags=["gateway"])


class PreconditionFailed(ServiceError):
    status = 412
    code = "not_cached"


def response_format(requested: str | None, accept: str) -> str:
    """``file``, ``raw`` or ``car``: the ``format`` parameter wins over ``Accept``."""
    if requested is not None:
        if requested not in FORMATS:
            raise BadRequest(
                f"unsupported format {requested!r}: expected raw or car",
                code="invalid_format",
                details={"field": "format"},
            )
        return requested
    offered = [part.split(";")[0].strip().lower() for part in accept.split(",")]
    for name, media in FORMATS.items():
        if media in offered:
            return name
    return "file"


def _headers(cid: CID, etag: str) -> dict[str, str]:
    return {
        "ETag": etag,
        "Cache-Control": IMMUTABLE,
        "X-Ipfs-Path": f"/ipfs/{cid}",
        "X-Ipfs-Roots": str(cid),
        "X-Content-Type-Options": "nosniff",
        "Vary": "Accept",
    }


def _not_modified(request: Request, etag: str) -> bool:
    offered = request.headers.get("if-none-match", "")
    return etag in (tag.strip() for tag in offered.split(",")) or offered.strip() == "*"


@router.api_route("/ipfs/{cid}", methods=["GET", "HEAD"])
async def ipfs(
    request: Request,
    cid: str,
    format: Annotated[str | None, Query(description="raw (one block) or car (a DAG)")] = None,
    dag_scope: Annotated[str, Query(alias="dag-scope", description="block, entity or all")] = "all",
) -> Response:
    """Content by CID: every byte can be checked against the CID by the client."""
    root = parse_cid(cid, "cid")
    store: ContentStore = request.app.state.store
    use_peers = "only-if-cached" not in request.headers.get("cache-control", "").lower()
    kind = response_format(format, request.headers.get("accept", ""))
    head = request.method == "HEAD"
    try:
        if kind == "raw":
            return await _raw(request, store, root, use_peers, head)
        if kind == "car":
            return await _car(request, store, root, dag_scope, use_peers, head)
        return await _file(request, store, root, use_peers, head)
    except BlockUnavailable as miss:
        if not use_peers:
            raise PreconditionFailed(
                f"{root} is not in this gateway's store", details={"cid": str(root)}
            ) from miss
        raise


async def _raw(
    request: Request, store: ContentStore, root: CID, use_peers: bool, head: bool
) -> Response:
    etag = f'"{root}.raw"'
    headers = _headers(root, etag) | {
        "Content-Disposition": f'attachment; filename="{root}.bin"',
    }
    if _not_modified(request, etag):
        return Response(status_code=304, headers=headers)
    data = await anyio.to_thread.run_sync(lambda: store.get_block(root, use_peers=use_peers))
    if head:
        headers["Content-Length"] = str(len(data))
        return Response(status_code=200, headers=headers, media_type=RAW_MEDIA_TYPE)
    return Response(data, headers=headers, media_type=RAW_MEDIA_TYPE)


async def _car(
    request: Request, store: ContentStore, root: CID, scope: str, use_peers: bool, head: bool
) -> Response:
    etag = f'"{root}.car.{scope}"'
    headers = _headers(root, etag) | {
        "Content-Disposition": f'attachment; filename="{root}.car"',
    }
    media_type = f"{CAR_MEDIA_TYPE}; version=1; order=dfs; dups=n"
    if _not_modified(request, etag):
        return Response(status_code=304, headers=headers)
    body = await threaded_stream(store.export_car(root, scope, use_peers=use_peers))
    if head:
        await body.aclose()
        return Response(status_code=200, headers=headers, media_type=media_type)
    return StreamingResponse(body, headers=headers, media_type=media_type)


async def _file(
    request: Request, store: ContentStore, root: CID, use_peers: bool, head: bool
) -> Response:
    etag = f'"{root}"'
    headers = _headers(root, etag) | {"Accept-Ranges": "bytes"}
    if _not_modified(request, etag):
        return Response(status_code=304, headers=headers)
    size = await anyio.to_thread.run_sync(lambda: store.file_size(root, use_peers=use_peers))
    span = byte_range(request.headers.get("range"), size)
    start, end = span or (0, size)
    status = 200
    if span is not None:
        status = 206
        headers["Content-Range"] = f"bytes {start}-{end - 1}/{size}"
    headers["Content-Length"] = str(end - start)
    media_type = "application/octet-stream"
    if head:
        return Response(status_code=status, headers=headers, media_type=media_type)
    body = await threaded_stream(store.read(root, start, end - start, use_peers=use_peers))
    return StreamingResponse(body, status_code=status, headers=headers, media_type=media_type)
