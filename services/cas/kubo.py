"""The kubo RPC subset (``/api/v0``) that IPFS clients and tools call.

Names, parameters and answer shapes follow kubo so that existing clients work unchanged;
errors use robocloud's JSON error model. Writes (add, block/put, dag/import, pin/add,
pin/rm, repo/gc) must be signed; reads are POSTs like in kubo but need no signature.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Iterator
from functools import partial
from typing import Annotated, Any

import anyio
from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import JSONResponse, Response

import robocloud
from robocloud.cid import CID, CODEC_NAMES, parse_cid
from robocloud.directory import Resolved
from robocloud.ledger.models import Role
from robocloud.unixfs import DIRECTORY, FILE, HAMT_SHARD, ImportParams, UnixfsError
from services.cas.gateway import file_answer, streamed
from services.cas.shares import UNBOUNDED, Share
from services.cas.store import BudgetedReads, ContentStore
from services.cas.uploads import Added, BlockCollector, CarImport, FileAdder, upload
from services.common.auth import SignedAddress
from services.common.errors import BadRequest
from services.common.slots import Slots

READ_PATHS = (
    "/api/v0/cat",
    "/api/v0/ls",
    "/api/v0/block/get",
    "/api/v0/block/stat",
    "/api/v0/pin/ls",
    "/api/v0/dag/export",
    "/api/v0/repo/stat",
    "/api/v0/version",
)
"""POST routes that only read: public, like every GET."""

CODECS = {name: code for code, name in CODEC_NAMES.items()}
CHUNKED = {"X-Chunked-Output": "1"}

router = APIRouter(prefix="/api/v0", tags=["kubo rpc"])

Arg = Annotated[str, Query(description="a CID")]
Args = Annotated[list[str], Query(description="one or more CIDs")]


async def _signer_share(request: Request, address: SignedAddress) -> Share:
    """What the signer may take of the store (``ROBOCLOUD_CAS_MAX_PINNED_BYTES_PER_ROBOT``,
    ``ROBOCLOUD_CAS_MAX_WRITTEN_BYTES_PER_ROBOT_PER_HOUR``), unbounded for a storage node
    (it stores every robot's bags under its own key) and the operator's keys. Asked before
    the body is read."""
    if await request.app.state.authorizer.holds_role(address, Role.STORAGE_NODE.value):
        return UNBOUNDED
    settings = request.app.state.settings
    return Share(
        settings.cas_max_pinned_bytes_per_robot,
        settings.cas_max_written_bytes_per_robot_per_hour,
    )


SignerShare = Annotated[Share, Depends(_signer_share)]


def _store(request: Request) -> ContentStore:
    store: ContentStore = request.app.state.store
    return store


async def _lines(objects: Iterable[dict[str, Any]]) -> Response:
    """kubo's streamed answer: one JSON object a line, encoded on a worker thread.

    Answers run to many lines (an ``add`` of 250,000 entries, a collection's every removed
    block; a ``dag/import`` of 409,600 roots was 103 MiB before roots were bounded), and
    encoding them on the event loop held every other request meanwhile.
    """

    def encode() -> str:
        return "".join(json.dumps(item, separators=(",", ":")) + "\n" for item in objects)

    body = await anyio.to_thread.run_sync(encode)
    return Response(body, media_type="application/json", headers=CHUNKED)


def _import_params(
    cid_version: int | None, raw_leaves: bool | None, chunker: str | None, profile: str | None
) -> ImportParams:
    try:
        return ImportParams.from_options(cid_version, raw_leaves, chunker, profile)
    except UnixfsError as exc:
        raise BadRequest(str(exc), code="invalid_import_options") from exc


ADD_OPTIONS = frozenset(
    {
        *("cid-version", "raw-leaves", "chunker", "profile", "pin", "only-hash"),
        *("wrap-with-directory", "progress", "hash", "trickle", "inline", "nocopy", "fscache"),
        *("quiet", "quieter", "silent", "stream-channels", "recursive"),
    }
)
"""kubo's ``add`` parameters robocloud honours; the presentation ones (``quiet`` and its
kin, ``stream-channels``, ``recursive``) only shape what kubo's own CLI prints or reads."""
NOT_IMPLEMENTED = {"trickle": "true", "inline": "true", "nocopy": "true", "fscache": "true"}


def _refuse_unimplemented(request: Request, hash_function: str) -> None:
    """Every option is honoured or refused: never a CID for another layout than asked for."""
    for name in request.query_params:
        if name not in ADD_OPTIONS:
            raise BadRequest(
                f"the add option {name!r} is not supported by this gateway",
                code="unsupported_option",
                details={"field": name},
            )
    for name, refused in NOT_IMPLEMENTED.items():
        if request.query_params.get(name, "false").lower() == refused:
            raise BadRequest(
                f"{name}={refused} is not supported: CIDs would differ from kubo's",
                code="unsupported_option",
                details={"field": name},
            )
    if hash_function != "sha2-256":
        raise BadRequest(
            f"unsupported hash {hash_function!r}: only sha2-256",
            code="unsupported_option",
            details={"field": "hash"},
        )


@router.post("/add")
async def add(
    request: Request,
    address: SignedAddress,
    share: SignerShare,
    cid_version: Annotated[int | None, Query(alias="cid-version")] = None,
    raw_leaves: Annotated[bool | None, Query(alias="raw-leaves")] = None,
    chunker: Annotated[str | None, Query(description="size-<bytes>")] = None,
    profile: Annotated[str | None, Query(description="unixfs-v0-2015 or unixfs-v1-2025")] = None,
    pin: bool = True,
    only_hash: Annotated[bool, Query(alias="only-hash")] = False,
    wrap_with_directory: Annotated[bool, Query(alias="wrap-with-directory")] = False,
    progress: bool = False,
    hash_function: Annotated[str, Query(alias="hash")] = "sha2-256",
) -> Response:
    """Add files and directories from kubo's multipart body (``ipfs add -r``, ``-w``).

    The answer has one ``{"Name","Hash","Size"}`` line per file, then per directory (after
    its contents), as kubo's; with ``progress``, a ``{"Name","Bytes"}`` line before each file.
    """
    _refuse_unimplemented(request, hash_function)
    params = _import_params(cid_version, raw_leaves, chunker, profile)
    adder = FileAdder(
        _store(request),
        params,
        only_hash=only_hash,
        pin=pin,
        wrap=wrap_with_directory,
        max_parts=request.app.state.settings.cas_max_upload_entries,
    )
    content_type = request.headers.get("content-type")
    added = await upload(request.stream(), content_type, adder, address, share)
    return await _lines(_added_lines(added, progress))


def _added_lines(added: list[Added], progress: bool) -> Iterator[dict[str, Any]]:
    """``add``'s lines, made as ``_lines`` encodes them, off the event loop."""
    for item in added:
        if progress and item.file_size is not None:
            yield {"Name": item.name, "Bytes": item.file_size}
        yield {"Name": item.name, "Hash": str(item.cid), "Size": str(item.dag_size)}


def _content_path(resolve: Callable[[CID, list[str]], Resolved], arg: str) -> Resolved:
    """kubo's ``arg`` of a path: ``CID[/segment...]``, optionally after ``/ipfs/``, followed
    by ``resolve`` (the store's, or a request's ``BudgetedReads``)."""
    text = arg.removeprefix("/ipfs/")
    cid_text, _, rest = text.partition("/")
    root = parse_cid(cid_text, "arg")
    segments = [segment for segment in rest.split("/") if segment] if rest else []
    if any(segment in (".", "..") for segment in segments):
        raise BadRequest(
            f"path {arg[:120]!r} has a . or .. segment",
            code="invalid_path",
            details={"field": "arg"},
        )
    return resolve(root, segments)


@router.post("/cat")
async def cat(
    request: Request,
    arg: Annotated[str, Query(description="a CID, or CID/path/to/file")],
    offset: Annotated[int, Query(ge=0)] = 0,
    length: Annotated[int | None, Query(ge=0)] = None,
) -> Response:
    """A file's bytes (or ``length`` of them from ``offset``), every block verified on read."""
    store = _store(request)
    target, size = await anyio.to_thread.run_sync(_file_and_size, store, arg)
    wanted = max(size - offset, 0) if length is None else min(length, max(size - offset, 0))
    chunks = store.read(target, offset, length)
    return await file_answer(request, chunks, wanted, media_type="application/octet-stream")


def _file_and_size(store: ContentStore, arg: str) -> tuple[CID, int]:
    """The file ``arg`` names, its path read within ``WALK_READ_BYTES`` (as the gateway's)."""
    reads = BudgetedReads.walk(store, field="arg")
    target = _content_path(reads.resolve, arg).cid
    return target, store.file_size(target)


MAX_LS_ARGS = 64
"""Directories one ``ls`` lists: a URL holds over a hundred ``arg``s, each a listing."""
LS_READ_BYTES = 256 * 1024 * 1024
"""Bytes of blocks one ``ls`` reads at most, over all its ``arg``s: directory nodes, shards,
and each distinct dag-pb entry's root block (for its type and size; a raw entry's size comes
from the block index). About a quarter of a second of hashing; a directory of 1,000 CIDv0
files of 256 KiB (each a dag-pb leaf holding its bytes) fits."""


@router.post("/ls")
async def ls(
    request: Request,
    arg: Annotated[list[str], Query(description="directories: CID or CID/path")],
    resolve_type: Annotated[bool, Query(alias="resolve-type")] = True,
    size: bool = True,
) -> Response:
    """A directory's entries, kubo's answer shape; ``Type`` 1 is a directory, 2 a file.

    Read (a block per distinct entry for its type and size, within ``LS_READ_BYTES``) and
    encoded on a worker thread, in the gateway's listing turns: a directory of 20,000 entries
    is free to ask for again and again.
    """
    if len(arg) > MAX_LS_ARGS:
        raise BadRequest(
            f"{len(arg)} arg values: ls lists at most {MAX_LS_ARGS} directories a request",
            code="too_many_arguments",
            details={"field": "arg", "limit": MAX_LS_ARGS},
        )
    store = _store(request)

    def answer() -> Response:
        reads = BudgetedReads(store, LS_READ_BYTES, field="arg")
        objects = [_listing(reads, path, resolve_type, size) for path in arg]
        return JSONResponse({"Objects": objects})

    slots: Slots = request.app.state.listing_slots
    return await slots.run_sync(answer)


def _listing(reads: BudgetedReads, path: str, resolve_type: bool, size: bool) -> dict[str, Any]:
    """One ``ls`` object: the entries of the directory ``path`` names."""
    directory = _content_path(reads.resolve, path).cid
    links = []
    for entry in reads.entries(directory):
        kind = reads.kind(entry.cid) if resolve_type or size else None
        links.append(
            {
                "Name": entry.name,
                "Hash": str(entry.cid),
                "Size": (kind.size or 0) if kind is not None and size else 0,
                "Type": _LS_TYPES.get(kind.type, 0) if kind is not None and resolve_type else 0,
                "Target": "",
            }
        )
    return {"Hash": path, "Links": links}


_LS_TYPES: dict[int | None, int] = {DIRECTORY: 1, HAMT_SHARD: 1, FILE: 2}
"""kubo's ``ls`` types: its UnixFS protobuf numbers for directories and files."""


@router.post("/block/get")
async def block_get(request: Request, arg: Arg) -> Response:
    cid = parse_cid(arg, "arg")
    data = await anyio.to_thread.run_sync(_store(request).get_block, cid)
    return Response(data, media_type="application/octet-stream")


@router.post("/block/stat")
async def block_stat(request: Request, arg: Arg) -> dict[str, Any]:
    cid = parse_cid(arg, "arg")
    size = await anyio.to_thread.run_sync(_store(request).block_size, cid)
    return {"Key": str(cid), "Size": size}


@router.post("/block/put")
async def block_put(
    request: Request,
    address: SignedAddress,
    share: SignerShare,
    cid_codec: Annotated[str, Query(alias="cid-codec")] = "raw",
    mhtype: str = "sha2-256",
    pin: bool = False,
) -> Response:
    """Store raw blocks as sent; answers ``{"Key","Size"}`` per block.

    With ``pin`` each block's DAG must be whole (from this request, the store or a peer),
    else 404 ``block_not_found`` and nothing is stored.
    """
    if cid_codec not in CODECS:
        raise BadRequest(
            f"unsupported cid-codec {cid_codec!r}: expected one of {', '.join(CODECS)}",
            code="invalid_codec",
            details={"field": "cid-codec"},
        )
    if mhtype != "sha2-256":
        raise BadRequest(
            f"unsupported mhtype {mhtype!r}: only sha2-256",
            code="invalid_hash",
            details={"field": "mhtype"},
        )
    collector = BlockCollector(_store(request), CODECS[cid_codec], pin=pin)
    content_type = request.headers.get("content-type")
    blocks = await upload(request.stream(), content_type, collector, address, share)
    return await _lines({"Key": str(block.cid), "Size": len(block.data)} for block in blocks)


@router.post("/pin/add")
async def pin_add(
    request: Request,
    address: SignedAddress,
    share: SignerShare,
    arg: Args,
    recursive: bool = True,
) -> dict[str, list[str]]:
    """Pin DAGs for the signing robot, all or none; every block must be here or at a peer,
    and the pins within the robot's share (507 ``quota_exceeded``)."""
    if not recursive:
        raise BadRequest(
            "only recursive pins are supported", code="unsupported", details={"field": "recursive"}
        )
    roots = [parse_cid(text, "arg") for text in arg]
    pin = partial(_store(request).pin, share=share)
    await anyio.to_thread.run_sync(pin, roots, address)
    return {"Pins": [str(root) for root in roots]}


@router.post("/pin/rm")
async def pin_rm(request: Request, address: SignedAddress, arg: Args) -> dict[str, list[str]]:
    """Remove the signing robot's own pins; another robot's pin is 403."""
    roots = [parse_cid(text, "arg") for text in arg]
    await anyio.to_thread.run_sync(_store(request).unpin, roots, address)
    return {"Pins": [str(root) for root in roots]}


@router.post("/pin/share")
async def pin_share(request: Request, address: SignedAddress, share: SignerShare) -> dict[str, Any]:
    """The signer's pinned bytes and new bytes written in the last hour, with the most it
    may keep and write (null: no bound), robocloud's addition to kubo's RPC: what a robot
    checks before an upload. Signed, so that a stranger cannot have the cas ask the ledger
    about address after address."""
    pinned, written = await anyio.to_thread.run_sync(_usage, _store(request), address)
    return {
        "Robot": address,
        "PinnedBytes": pinned,
        "MaxBytes": share.max_pinned_bytes,
        "WrittenBytesLastHour": written,
        "MaxWrittenBytesPerHour": share.max_written_bytes_per_hour,
    }


def _usage(store: ContentStore, address: str) -> tuple[int, int]:
    """``address``'s pinned bytes and bytes written in the last hour, asked on a worker
    thread: the pins' lock is held across the journal's fsync of every pin and unpin."""
    return store.pins.pinned_bytes(address), store.writes.written(address)


@router.post("/pin/ls")
async def pin_ls(
    request: Request,
    arg: Annotated[list[str] | None, Query(description="only these CIDs")] = None,
    type: Annotated[str, Query(description="all or recursive")] = "all",
) -> Response:
    """Pinned roots with their owners (``Owners`` is robocloud's addition to kubo's answer)."""
    if type not in ("all", "recursive"):
        return JSONResponse({"Keys": {}})
    wanted = [parse_cid(text, "arg") for text in arg or []]
    return await anyio.to_thread.run_sync(_pin_keys, _store(request), wanted)


def _pin_keys(store: ContentStore, wanted: list[CID]) -> Response:
    """``pin/ls``'s answer, made and encoded on a worker thread: the pins' snapshot waits for
    their lock, held across the journal's fsync of every pin and unpin, and the answer is a
    line per pinned root."""
    pins = store.pinned(wanted)
    keys = {str(cid): {"Type": "recursive", "Owners": sorted(pins[cid])} for cid in pins}
    return JSONResponse({"Keys": keys})


@router.post("/dag/export")
async def dag_export(request: Request, arg: Arg) -> Response:
    """The whole DAG under a root as a CARv1 stream."""
    root = parse_cid(arg, "arg")
    chunks = _store(request).export_car(root, "all")
    return await streamed(request, chunks, media_type="application/vnd.ipld.car")


@router.post("/dag/import")
async def dag_import(
    request: Request,
    address: SignedAddress,
    share: SignerShare,
    pin_roots: Annotated[bool, Query(alias="pin-roots")] = True,
    stats: bool = False,
) -> Response:
    """Import CARs: every block is verified, and one bad block rejects the whole upload.
    With ``stats``, a last line counts the blocks and bytes read, as kubo's."""
    car_import = CarImport(_store(request), pin_roots=pin_roots)
    content_type = request.headers.get("content-type")
    roots = await upload(request.stream(), content_type, car_import, address, share)
    lines: list[dict[str, Any]] = [
        {"Root": {"Cid": {"/": str(root.cid)}, "PinErrorMsg": root.pin_error}} for root in roots
    ]
    if stats:
        counted = car_import.stats
        lines.append({"Stats": {"BlockCount": counted.blocks, "BlockBytesCount": counted.bytes}})
    return await _lines(lines)


@router.post("/repo/gc")
async def repo_gc(request: Request, _: SignedAddress) -> Response:
    """Remove unpinned blocks older than the grace period now; answers each removed key."""
    grace = request.app.state.settings.cas_gc_grace_s
    removed = await anyio.to_thread.run_sync(_store(request).collect_garbage, grace)
    return await _lines({"Key": {"/": str(cid)}} for cid in removed)


@router.post("/repo/stat")
async def repo_stat(request: Request) -> dict[str, Any]:
    """Stored blocks and the bytes their packs use on disk."""
    count, size = await anyio.to_thread.run_sync(_store(request).usage)
    return {"NumObjects": count, "RepoSize": size, "RepoPath": "", "Version": "robocloud-packs-1"}


@router.api_route("/version", methods=["GET", "POST"])
async def version() -> dict[str, str]:
    """kubo clients call this to check that they reach an RPC endpoint."""
    return {"Version": robocloud.__version__, "System": "robocloud-cas", "Commit": "", "Repo": ""}
