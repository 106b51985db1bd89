"""The gateway: ``GET|HEAD /ipfs/{cid}[/{path}]`` as file bytes, a listing, a block, or a CAR.

Follows the IPFS trustless and path gateway specs for what a verifying client needs:
``format`` or ``Accept`` picks the response type, ``dag-scope`` and ``entity-bytes`` the CAR's
extent (after the blocks that verify each path segment), ``Range`` a byte range of a file,
``If-None-Match`` a 304, and ``Cache-Control: only-if-cached`` an answer from the local store
alone (412 on a miss), which is what peers ask each other. A directory answers its
``index.html`` when it holds one, else a listing (HTML, or the node as DAG-JSON).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated, Any
from urllib.parse import unquote

import anyio
from fastapi import APIRouter, Query, Request
from fastapi.responses import RedirectResponse, Response
from starlette.convertors import Convertor, register_url_convertor

from robocloud.cid import CID, DAG_PB, parse_cid
from robocloud.dagpb import DagPbError, PBNode, to_dag_json
from robocloud.directory import PathNotFound, Resolved
from robocloud.unixfs import DIRECTORY, FILE, HAMT_SHARD
from services.cas.listing import content_url, directory_page
from services.cas.ranges import EntityBytes, byte_range
from services.cas.store import (
    DAG_SCOPES,
    BlockUnavailable,
    ContentStore,
    InvalidDag,
    UnknownScope,
)
from services.cas.streams import BATCH_BYTES, threaded_stream
from services.common.errors import BadRequest, ServiceError
from services.common.responses import stream_in_turn
from services.common.slots import Slots

RAW_MEDIA_TYPE = "application/vnd.ipld.raw"
CAR_MEDIA_TYPE = "application/vnd.ipld.car"
DAG_JSON_MEDIA_TYPE = "application/vnd.ipld.dag-json"
IMMUTABLE = "public, max-age=29030400, immutable"
FORMATS = {"raw": RAW_MEDIA_TYPE, "car": CAR_MEDIA_TYPE, "dag-json": DAG_JSON_MEDIA_TYPE}
MAX_PATH_SEGMENTS = 256
LISTING_TURNS = 2
LISTING_WAIT_S = 5.0
"""Directory listings (the gateway's HTML and dag-json, kubo's ``ls``) take turns
(``services.common.slots``): a directory of 20,000 entries is 0.4-0.6 s of CPU and 5.7 MB of
HTML, free for anyone to ask again and again."""


class AnyPath(Convertor[str]):
    """Starlette's ``{path:path}`` with ``.`` matching newlines too.

    Its ``.*`` stops at ``\\n``, so an entry whose name holds one (any UTF-8 is a valid dag-pb
    name) had no route at all: 404 "no route" instead of the entry or ``path_not_found``.
    The path itself is read from ``raw_path`` (``content_path``), never from this parameter.
    """

    regex = "(?s:.*)"

    def convert(self, value: str) -> str:
        return value

    def to_string(self, value: str) -> str:
        return value


register_url_convertor("anypath", AnyPath())

router = APIRouter(tags=["gateway"])


class PreconditionFailed(ServiceError):
    status = 412
    code = "not_cached"


def response_format(requested: str | None, accept: str) -> str:
    """``file``, ``raw``, ``car`` or ``dag-json``: the ``format`` parameter wins over ``Accept``."""
    if requested is not None:
        if requested not in FORMATS:
            raise BadRequest(
                f"unsupported format {requested!r}: expected {', '.join(FORMATS)}",
                code="invalid_format",
                details={"field": "format"},
            )
        return requested
    offered = [part.split(";")[0].strip().lower() for part in accept.split(",")]
    for name, media in FORMATS.items():
        if media in offered:
            return name
    return "file"


def car_params(scope: str, entity_range: str | None) -> tuple[str, EntityBytes | None]:
    """A CAR's ``dag-scope`` and ``entity-bytes``, checked before anything is looked up.

    A bad value is 400 whatever the path names and whatever ``If-None-Match`` says: the raw
    value used to reach the ``ETag`` unchecked (CR/LF in it broke the response, non-ASCII was
    500) and a bogus scope was answered 304 to ``If-None-Match: *``. A well-formed range
    implies ``dag-scope=entity``, as the trustless gateway specification says.
    """
    if scope not in DAG_SCOPES:
        raise UnknownScope(scope)
    if entity_range is None:
        return scope, None
    return "entity", EntityBytes.parse(entity_range)


def content_path(request: Request, cid: str) -> tuple[list[str], bool]:
    """The path's segments after ``/ipfs/{cid}``, percent-decoded one by one, and whether it
    ends with ``/``. Decoding each segment apart keeps an escaped ``/`` inside a name."""
    raw = request.scope.get("raw_path", request.url.path.encode()).split(b"?", 1)[0]
    rest = raw.decode("latin-1").split("/")[3:]
    trailing = len(rest) > 0 and rest[-1] == ""
    if trailing:
        rest = rest[:-1]
    if len(rest) > MAX_PATH_SEGMENTS:
        raise BadRequest(
            f"a path of more than {MAX_PATH_SEGMENTS} segments",
            code="invalid_path",
            details={"path": f"/ipfs/{cid}/..."},
        )
    segments = []
    for encoded in rest:
        try:
            segment = unquote(encoded, errors="strict")
        except UnicodeDecodeError:
            segment = ""
        if segment in ("", ".", "..") or "\x00" in segment:
            raise BadRequest(
                f"path segment {encoded[:80]!r} is empty, `.`, `..` or not UTF-8",
                code="invalid_path",
                details={"segment": encoded[:80]},
            )
        segments.append(segment)
    return segments, trailing


def _headers(root: CID, path: list[str], target: CID, etag: str) -> dict[str, str]:
    return {
        "ETag": etag,
        "Cache-Control": IMMUTABLE,
        "X-Ipfs-Path": content_url(root, path),
        "X-Ipfs-Roots": str(target),
        "X-Content-Type-Options": "nosniff",
        "Vary": "Accept",
    }


def _not_modified(request: Request, etag: str) -> bool:
    offered = request.headers.get("if-none-match", "")
    return etag in (tag.strip() for tag in offered.split(",")) or offered.strip() == "*"


@router.api_route("/ipfs/{cid}", methods=["GET", "HEAD"])
@router.api_route("/ipfs/{cid}/{path:anypath}", methods=["GET", "HEAD"])
async def ipfs(
    request: Request,
    cid: str,
    format: Annotated[
        str | None, Query(description="raw (one block), car (a DAG) or dag-json (a node)")
    ] = None,
    dag_scope: Annotated[str, Query(alias="dag-scope", description="block, entity or all")] = "all",
    entity_range: Annotated[
        str | None, Query(alias="entity-bytes", description="from:to of a file, for a CAR")
    ] = None,
) -> Response:
    """Content by CID and path: every byte can be checked against the CID by the client."""
    root = parse_cid(cid, "cid")
    segments, trailing = content_path(request, cid)
    store: ContentStore = request.app.state.store
    use_peers = "only-if-cached" not in request.headers.get("cache-control", "").lower()
    kind = response_format(format, request.headers.get("accept", ""))
    scope, entity = car_params(dag_scope, entity_range) if kind == "car" else ("all", None)
    head = request.method == "HEAD"
    try:
        resolved = await anyio.to_thread.run_sync(
            lambda: store.resolve(root, segments, use_peers=use_peers)
        )
        if kind == "car":
            return await _car(request, store, root, segments, resolved, scope, entity)
        if kind == "raw":
            return await _raw(request, store, root, segments, resolved.cid, use_peers, head)
        if kind == "dag-json":
            return await _dag_json(request, store, root, segments, resolved.cid, use_peers, head)
        return await _content(request, store, root, segments, trailing, resolved.cid, use_peers)
    except BlockUnavailable as miss:
        if not use_peers:
            raise PreconditionFailed(
                f"{miss.cid} is not in this gateway's store", details={"cid": str(miss.cid)}
            ) from miss
        raise


async def _raw(
    request: Request,
    store: ContentStore,
    root: CID,
    path: list[str],
    target: CID,
    use_peers: bool,
    head: bool,
) -> Response:
    etag = f'"{target}.raw"'
    headers = _headers(root, path, target, etag) | {
        "Content-Disposition": f'attachment; filename="{target}.bin"',
    }
    if _not_modified(request, etag):
        return Response(status_code=304, headers=headers)
    data = await anyio.to_thread.run_sync(lambda: store.get_block(target, use_peers=use_peers))
    if head:
        headers["Content-Length"] = str(len(data))
        return Response(status_code=200, headers=headers, media_type=RAW_MEDIA_TYPE)
    return Response(data, headers=headers, media_type=RAW_MEDIA_TYPE)


async def _car(
    request: Request,
    store: ContentStore,
    root: CID,
    path: list[str],
    resolved: Resolved,
    scope: str,
    entity_range: EntityBytes | None,
) -> Response:
    use_peers = "only-if-cached" not in request.headers.get("cache-control", "").lower()
    span = None
    if entity_range is not None:
        target = await anyio.to_thread.run_sync(
            lambda: store.kind(resolved.cid, use_peers=use_peers)
        )
        if target.type == FILE and target.size is not None:
            span = entity_range.within(target.size)
    etag = f'"{resolved.cid}.car.{scope}.{entity_range or ""}"'
    headers = _headers(root, path, resolved.cid, etag) | {
        "Content-Disposition": f'attachment; filename="{resolved.cid}.car"',
    }
    media_type = f"{CAR_MEDIA_TYPE}; version=1; order=dfs; dups=n"
    if _not_modified(request, etag):
        return Response(status_code=304, headers=headers)
    blocks = store.export_path_car(root, resolved, scope, span, use_peers=use_peers)
    if request.method == "HEAD":
        body = await threaded_stream(blocks)
        await body.aclose()
        return Response(status_code=200, headers=headers, media_type=media_type)
    return await streamed(request, blocks, headers=headers, media_type=media_type)


async def _dag_json(
    request: Request,
    store: ContentStore,
    root: CID,
    path: list[str],
    target: CID,
    use_peers: bool,
    head: bool,
) -> Response:
    if target.codec != DAG_PB:
        raise BadRequest(
            f"{target} is not a dag-pb node: ask for format=raw",
            code="invalid_format",
            details={"field": "format", "cid": str(target)},
        )
    etag = f'"{target}.dag-json"'
    headers = _headers(root, path, target, etag)
    if _not_modified(request, etag):
        return Response(status_code=304, headers=headers)
    slots: Slots = request.app.state.listing_slots
    body = await slots.run_sync(lambda: _node_as_dag_json(store, target, use_peers))
    headers["Content-Length"] = str(len(body))
    return Response(b"" if head else body, headers=headers, media_type=DAG_JSON_MEDIA_TYPE)


def _node_as_dag_json(store: ContentStore, target: CID, use_peers: bool) -> bytes:
    """The dag-pb node ``target`` in dag-json, read and converted in a listing turn.

    A node is a listing by another name: 8 MB of 65,536 links are about 0.8 s of CPU to
    decode and encode, and this ran on the event loop, so 20 requests at once held every
    route for 12.5 s. It now takes the turns the HTML page and ``ls`` take (HEAD too, which
    needs the length).
    """
    data = store.get_block(target, use_peers=use_peers)
    try:
        node = PBNode.decode(data)
    except DagPbError as exc:
        raise InvalidDag(target, f"{target} is not a dag-pb node: {exc}") from exc
    return to_dag_json(node)


async def _content(
    request: Request,
    store: ContentStore,
    root: CID,
    path: list[str],
    trailing: bool,
    target: CID,
    use_peers: bool,
) -> Response:
    kind = await anyio.to_thread.run_sync(lambda: store.kind(target, use_peers=use_peers))
    if kind.type not in (DIRECTORY, HAMT_SHARD):
        return await _file(request, store, root, path, target, use_peers)
    try:
        index = await anyio.to_thread.run_sync(
            lambda: store.resolve(target, ["index.html"], use_peers=use_peers)
        )
    except PathNotFound:
        return await _listing(request, store, root, path, target, use_peers)
    if not trailing:
        return RedirectResponse(content_url(root, path) + "/", status_code=301)
    response = await _file(request, store, root, path, index.cid, use_peers)
    response.headers["Content-Type"] = "text/html; charset=utf-8"
    response.headers["Content-Security-Policy"] = "sandbox"
    return response


async def _listing(
    request: Request, store: ContentStore, root: CID, path: list[str], target: CID, use_peers: bool
) -> Response:
    etag = f'"{target}.listing"'
    headers = _headers(root, path, target, etag)
    if _not_modified(request, etag):
        return Response(status_code=304, headers=headers)

    def render() -> bytes:
        entries = store.entries(target, use_peers=use_peers)
        return directory_page(root, path, target, entries).encode()

    slots: Slots = request.app.state.listing_slots
    page = await slots.run_sync(render)
    headers["Content-Length"] = str(len(page))
    body = b"" if request.method == "HEAD" else page
    return Response(body, headers=headers, media_type="text/html; charset=utf-8")


async def _file(
    request: Request, store: ContentStore, root: CID, path: list[str], target: CID, use_peers: bool
) -> Response:
    etag = f'"{target}"'
    headers = _headers(root, path, target, etag) | {"Accept-Ranges": "bytes"}
    if _not_modified(request, etag):
        return Response(status_code=304, headers=headers)
    size = await anyio.to_thread.run_sync(lambda: store.file_size(target, use_peers=use_peers))
    span = byte_range(request.headers.get("range"), size)
    start, end = span or (0, size)
    status = 200
    if span is not None:
        status = 206
        headers["Content-Range"] = f"bytes {start}-{end - 1}/{size}"
    headers["Content-Length"] = str(end - start)
    media_type = "application/octet-stream"
    if request.method == "HEAD":
        return Response(status_code=status, headers=headers, media_type=media_type)
    chunks = store.read(target, start, end - start, use_peers=use_peers)
    return await file_answer(
        request, chunks, end - start, status_code=status, headers=headers, media_type=media_type
    )


async def streamed(request: Request, chunks: Iterator[bytes], **response: Any) -> Response:
    """The answer streaming ``chunks`` (``threaded_stream``) in one of the app's stream turns
    (``stream_slots``); 503 ``busy`` when none came within its wait."""
    return await stream_in_turn(
        request.app.state.stream_slots, lambda: threaded_stream(chunks), **response
    )


async def file_answer(
    request: Request, chunks: Iterator[bytes], size: int, **response: Any
) -> Response:
    """``size`` bytes of a file: read whole and answered at once when they fit in one
    read-ahead batch, else ``streamed``. A small read needs no stream turn, so it goes on
    while large streams hold every turn (with 100 clients exporting 64 MiB DAGs, reading a
    five-byte file was 503 ``busy``)."""
    if size <= BATCH_BYTES:
        return Response(await anyio.to_thread.run_sync(b"".join, chunks), **response)
    return await streamed(request, chunks, **response)
