"""Cas routes whose lock-taking part is held (by garbage collection, or a pin's journal fsync,
in a running cas): the service's other routes answer meanwhile, as they do only when that part
runs on a worker thread rather than on the event loop. Served in process over
``httpx.ASGITransport`` through the whole app: its signature guard verifies the headers
itself, so writes carry real signatures (``auth=signed``) rather than ``tests.held.signed_by``."""

from __future__ import annotations

import asyncio
import hashlib
import io
import json
import threading
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from functools import partial
from pathlib import Path
from typing import Any

import anyio
import httpx
import pytest
from fastapi import FastAPI

from robocloud.car import CarReader
from robocloud.cid import CID, RAW, Block
from robocloud.identity import Identity
from robocloud.signing import sign_request
from robocloud.unixfs import Importer, ImportParams
from services.cas.app import build_app
from services.cas.settings import CasSettings
from services.cas.store import ContentStore, UnixfsKind
from tests.held import Gate, answered_while_held

BOUNDARY = "off-the-loop"
CHUNK = 1024

HeldRequest = Callable[[httpx.AsyncClient], Awaitable[httpx.Response]]


@pytest.fixture
def app(tmp_path: Path) -> Iterator[FastAPI]:
    built = build_app(CasSettings(data_dir=tmp_path, cas_gc_interval_s=0, auth="signed"))
    yield built
    built.state.store.close()
    built.state.nonces.close()


@pytest.fixture
def robot() -> Identity:
    return Identity.generate()


def store_of(app: FastAPI) -> ContentStore:
    store: ContentStore = app.state.store
    return store


def signed(app: FastAPI, robot: Identity, path: str, body: bytes = b"") -> dict[str, str]:
    """The signature headers of a POST to ``path`` (no query) carrying ``body``."""
    audience = str(app.state.audience.require())
    digest = hashlib.sha256(body).hexdigest()
    return sign_request(robot.account, audience, "POST", path, "", digest)


def multipart(name: str, data: bytes) -> bytes:
    """A kubo-style multipart body of one file, its boundary :data:`BOUNDARY`."""
    head = (
        f"--{BOUNDARY}\r\n"
        f'Content-Disposition: form-data; name="file"; filename="{name}"\r\n'
        "Content-Type: application/octet-stream\r\n\r\n"
    )
    return head.encode() + data + f"\r\n--{BOUNDARY}--\r\n".encode()


def upload_headers(app: FastAPI, robot: Identity, path: str, body: bytes) -> dict[str, str]:
    content_type = f"multipart/form-data; boundary={BOUNDARY}"
    return signed(app, robot, path, body) | {"Content-Type": content_type}


def packs(store: ContentStore) -> list[Path]:
    return sorted(store.blocks.packs.glob("*.pack"))


def held_beside_version(
    app: FastAPI, gate: Gate, held: HeldRequest
) -> tuple[httpx.Response, httpx.Response, bool]:
    """``held``'s answer, and ``GET /api/v0/version``'s, sent once ``gate`` holds ``held``
    and whether it was answered while the gate held."""

    async def go() -> tuple[httpx.Response, httpx.Response, bool]:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://cas") as client:
            answer, probes, answered_while = await answered_while_held(
                gate, held(client), {"version": lambda: client.get("/api/v0/version")}
            )
        return answer, probes["version"], answered_while["version"]

    return asyncio.run(go())


def assert_answered_while_held(probe: httpx.Response, answered_while: bool) -> None:
    assert probe.status_code == 200
    assert probe.json()["System"] == "robocloud-cas"
    assert answered_while, "the version probe waited for the held call: it ran on the event loop"


def hold_release(app: FastAPI, gate: Gate, monkeypatch: pytest.MonkeyPatch) -> None:
    """Hold the first hold given back: its ``sweeping`` lock is garbage collection's."""
    blocks = store_of(app).blocks
    monkeypatch.setattr(blocks, "_release", gate.wrap(blocks._release))


def test_add_answers_other_routes_while_its_discard_waits_for_the_sweep(
    app: FastAPI, robot: Identity, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``add`` gave its staging back (``sink.discard()``, the blockstore's ``sweeping`` lock,
    which garbage collection holds across fsyncs) on the event loop, after the commit: a
    sweep held every route of the cas. The answer still comes once it is given back, and
    the file is stored and pinned."""
    gate = Gate()
    hold_release(app, gate, monkeypatch)
    content = b"added while the sweep runs\n"
    body = multipart("a.txt", content)
    headers = upload_headers(app, robot, "/api/v0/add", body)

    answer, probe, answered_while = held_beside_version(
        app, gate, lambda client: client.post("/api/v0/add", content=body, headers=headers)
    )

    assert_answered_while_held(probe, answered_while)
    assert answer.status_code == 200, answer.text
    root, blocks = imported(content, ImportParams.from_options())
    size = sum(len(block.data) for block in blocks)
    lines = [json.loads(text) for text in answer.text.splitlines()]
    assert lines == [{"Name": "a.txt", "Hash": str(root), "Size": str(size)}]
    store = store_of(app)
    assert store.pins.owners(root) == {robot.address}
    assert b"".join(store.read(root)) == content


def test_a_refused_dag_import_answers_other_routes_while_its_discard_waits(
    app: FastAPI, robot: Identity, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A failed ``dag/import`` joined its CAR reader and unlinked the staged pack (up to the
    upload limit, 4 GiB) on the event loop, behind the sweep's lock. Its 400 still comes
    once the staging is given back, with nothing stored."""
    gate = Gate()
    hold_release(app, gate, monkeypatch)
    body = multipart("bad.car", b"\xff not a CAR at all")
    headers = upload_headers(app, robot, "/api/v0/dag/import", body)

    answer, probe, answered_while = held_beside_version(
        app, gate, lambda client: client.post("/api/v0/dag/import", content=body, headers=headers)
    )

    assert_answered_while_held(probe, answered_while)
    assert answer.status_code == 400, answer.text
    assert answer.json()["error"]["code"] == "invalid_car"
    store = store_of(app)
    assert store.blocks.usage() == (0, 0)
    assert packs(store) == []


def test_an_add_cancelled_half_way_still_drops_its_staged_pack(
    app: FastAPI, robot: Identity
) -> None:
    """An upload cancelled mid-body (its cancel scope cancelled, which cancels every await
    inside it) still discards its staging, now awaited on a worker thread: unshielded, that
    await was cancelled before the thread started, and the staged pack stayed until a
    restart. Nothing is stored."""
    store = store_of(app)
    head = multipart("big.bin", b"").split(b"\r\n--" + BOUNDARY.encode() + b"--")[0]
    headers = upload_headers(app, robot, "/api/v0/add", b"")
    went_away = asyncio.Event()

    async def body() -> AsyncIterator[bytes]:
        yield head
        for _ in range(3):
            yield bytes(512 * 1024)
        await went_away.wait()

    async def go() -> None:
        transport = httpx.ASGITransport(app=app)
        async with (
            httpx.AsyncClient(transport=transport, base_url="http://cas") as client,
            anyio.create_task_group() as requests,
        ):
            requests.start_soon(
                partial(client.post, "/api/v0/add", content=body(), headers=headers)
            )
            while not any(pack.stat().st_size for pack in packs(store)):
                await anyio.sleep(0.01)
            requests.cancel_scope.cancel()

    asyncio.run(go())

    assert packs(store) == []
    assert store.blocks.usage() == (0, 0)


def test_pin_ls_answers_other_routes_while_the_pins_are_journalled(
    app: FastAPI, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``pin/ls`` took the pins' snapshot (their lock, held across the journal fsync of every
    pin and unpin) and built its answer, a line per pin, on the event loop."""
    store = store_of(app)
    owner = "0x" + "ab" * 20
    (cid,) = store.put_blocks([b"pinned"], RAW, owner, pin=True)
    gate = Gate()
    monkeypatch.setattr(store.pins, "snapshot", gate.wrap(store.pins.snapshot))

    answer, probe, answered_while = held_beside_version(
        app, gate, lambda client: client.post("/api/v0/pin/ls")
    )

    assert_answered_while_held(probe, answered_while)
    assert answer.status_code == 200, answer.text
    assert answer.json() == {"Keys": {str(cid): {"Type": "recursive", "Owners": [owner]}}}


def test_pin_share_answers_other_routes_while_the_pins_are_journalled(
    app: FastAPI, robot: Identity, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``pin/share`` read the signer's pinned bytes under the pins' lock, held across the
    journal fsync of every pin and unpin, on the event loop."""
    store = store_of(app)
    data = b"pinned by the signer"
    store.put_blocks([data], RAW, robot.address, pin=True)
    gate = Gate()
    monkeypatch.setattr(store.pins, "pinned_bytes", gate.wrap(store.pins.pinned_bytes))
    headers = signed(app, robot, "/api/v0/pin/share")

    answer, probe, answered_while = held_beside_version(
        app, gate, lambda client: client.post("/api/v0/pin/share", headers=headers)
    )

    assert_answered_while_held(probe, answered_while)
    assert answer.status_code == 200, answer.text
    settings: CasSettings = app.state.settings
    assert answer.json() == {
        "Robot": robot.address,
        "PinnedBytes": len(data),
        "MaxBytes": settings.cas_max_pinned_bytes_per_robot,
        "WrittenBytesLastHour": len(data),
        "MaxWrittenBytesPerHour": settings.cas_max_written_bytes_per_robot_per_hour,
    }


def imported(content: bytes, params: ImportParams) -> tuple[CID, list[Block]]:
    """``content`` as a UnixFS file: its root, and its blocks with the root last."""
    importer = Importer(params)
    blocks = importer.feed(content)
    tail, root, _ = importer.finish()
    return root, blocks + tail


def stored_file(store: ContentStore, content: bytes) -> tuple[CID, list[Block]]:
    """``content`` stored as a UnixFS file of :data:`CHUNK`-byte leaves (``imported``)."""
    root, blocks = imported(content, ImportParams.from_options(1, chunker=f"size-{CHUNK}"))
    for block in blocks:
        store.blocks.put(block.cid, block.data)
    return root, blocks


def lock_blocks_after_first_kind(
    store: ContentStore, gate: Gate, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Once the first ``kind`` returns, a thread takes the blockstore's lock (as garbage
    collection's deletes do, across index fsyncs) and keeps it while ``gate`` holds it."""
    kind = store.kind

    def locked() -> None:
        with store.blocks._lock:
            gate.hold()

    def kind_then_locked(cid: CID, **options: Any) -> UnixfsKind:
        found = kind(cid, **options)
        if not gate.entered.is_set():
            threading.Thread(target=locked, name="sweep", daemon=True).start()
            assert gate.entered.wait(5)
        return found

    monkeypatch.setattr(store, "kind", kind_then_locked)


def test_a_car_of_entity_bytes_answers_other_routes_while_the_blocks_are_locked(
    app: FastAPI, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``format=car&entity-bytes`` worked out the target's kind on a worker thread, then
    again on the event loop (``export_path_car``): a block read under the blockstore's lock
    (held by a collection's deletes) and a peer fetch past the read cache held every route.
    The CAR still holds the root and just the leaf covering the range."""
    store = store_of(app)
    root, blocks = stored_file(store, bytes(range(256)) * 12)
    gate = Gate()
    lock_blocks_after_first_kind(store, gate, monkeypatch)
    params = {"format": "car", "entity-bytes": f"{CHUNK}:{2 * CHUNK - 1}"}

    answer, probe, answered_while = held_beside_version(
        app, gate, lambda client: client.get(f"/ipfs/{root}", params=params)
    )

    assert_answered_while_held(probe, answered_while)
    assert answer.status_code == 200, answer.text
    reader = CarReader(io.BytesIO(answer.content))
    assert reader.roots == [root]
    assert [block.cid for block in reader] == [root, blocks[1].cid]
