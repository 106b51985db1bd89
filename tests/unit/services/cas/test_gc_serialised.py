"""One garbage collection at a time, and a compaction that outlives the pack it copies.

The periodic collection and ``repo/gc`` ran at once: both rewrote the same half-dead pack,
the first to finish deleted it, and the other failed reading it (a 500, or a crashed
periodic task). Each test stops a compaction while it copies, as the other one did.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from robocloud.cid import Block
from services.cas.blockstore import Staging
from services.cas.store import ContentStore
from tests.unit.services.cas.test_reachability import ALICE, put, raw

LEAVES = [raw(b"a pinned leaf"), raw(b"another pinned leaf")]
GARBAGE = raw(b"\x00" * 10_000)
"""Unpinned and larger than the leaves: once collected, their pack is more than half dead."""


class Watched:
    """A lock that says when a thread had to wait for it."""

    def __init__(self, lock: threading.Lock) -> None:
        self._lock = lock
        self.waited = threading.Event()

    def __enter__(self) -> None:
        if not self._lock.acquire(blocking=False):
            self.waited.set()
            self._lock.acquire()

    def __exit__(self, *exc_info: object) -> None:
        self._lock.release()


class Run(threading.Thread):
    """``target`` in a thread, keeping what it returned or raised."""

    def __init__(self, target: Callable[[], Any]) -> None:
        super().__init__()
        self._call = target
        self.result: Any = None
        self.error: BaseException | None = None
        self.start()

    def run(self) -> None:
        try:
            self.result = self._call()
        except BaseException as exc:  # handed to the test
            self.error = exc

    def outcome(self) -> Any:
        self.join(10)
        assert not self.is_alive()
        if self.error is not None:
            raise self.error
        return self.result


@pytest.fixture
def copying(
    store: ContentStore, monkeypatch: pytest.MonkeyPatch
) -> Iterator[tuple[threading.Event, threading.Event]]:
    """``LEAVES`` and ``GARBAGE`` in one pack, stored; then (reached, go): the first block a
    compaction copies waits for ``go``."""
    put(store, *LEAVES, GARBAGE)
    reached, go = threading.Event(), threading.Event()
    write = Staging.write

    def paused(staging: Staging, multihash: bytes, data: bytes | memoryview) -> None:
        if not reached.is_set():
            reached.set()
            assert go.wait(10)
        write(staging, multihash, data)

    monkeypatch.setattr(Staging, "write", paused)
    yield reached, go
    go.set()


def collect(store: ContentStore) -> list[bytes]:
    return [cid.multihash for cid in store.collect_garbage(grace_s=0, now=time.time() + 1)]


def test_a_second_collection_waits_for_the_first_compaction_included(
    store: ContentStore,
    monkeypatch: pytest.MonkeyPatch,
    copying: tuple[threading.Event, threading.Event],
) -> None:
    reached, go = copying
    store.pins.add_all({leaf.cid: len(leaf.data) for leaf in LEAVES}, ALICE)
    collecting = Watched(store.collecting)
    monkeypatch.setattr(store, "collecting", collecting)
    first = Run(lambda: collect(store))
    assert reached.wait(10)
    second = Run(lambda: collect(store))
    assert collecting.waited.wait(10)
    go.set()
    assert first.outcome() == [GARBAGE.cid.multihash]
    assert second.outcome() == []
    assert [store.blocks.get(leaf.cid) for leaf in LEAVES] == [leaf.data for leaf in LEAVES]
    assert len(list(store.blocks.packs.glob("*.pack"))) == 1


@pytest.mark.parametrize("deleted", [LEAVES[:1], LEAVES], ids=["one block", "every block"])
def test_blocks_deleted_while_their_pack_is_copied_stay_deleted(
    store: ContentStore, copying: tuple[threading.Event, threading.Event], deleted: list[Block]
) -> None:
    """A quarantine may delete blocks of the pack being compacted, even its last one."""
    reached, go = copying
    store.blocks.delete([GARBAGE.cid.multihash])
    compaction = Run(store.blocks.compact)
    assert reached.wait(10)
    store.blocks.delete([block.cid.multihash for block in deleted])
    go.set()
    compaction.outcome()
    kept = [leaf for leaf in LEAVES if leaf not in deleted]
    assert [store.blocks.has(leaf.cid) for leaf in LEAVES] == [leaf in kept for leaf in LEAVES]
    assert [store.blocks.get(leaf.cid) for leaf in kept] == [leaf.data for leaf in kept]
    assert len(list(store.blocks.packs.glob("*.idx"))) == len(
        list(store.blocks.packs.glob("*.pack"))
    )
    assert store.blocks.usage()[0] == len(kept)
