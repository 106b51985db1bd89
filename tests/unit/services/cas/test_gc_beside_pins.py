"""Garbage collection beside pins and uploads, in process, each interleaving forced.

A collection takes a snapshot of the pins, marks, then deletes; a pin checks its DAG, then
pins it; an upload skips blocks already stored, then commits and pins. Each test stops one
of them at the point where the other used to slip in: before the holds, every one of these
ended with a pinned DAG whose blocks were gone.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import pytest

from robocloud.cid import CID, DAG_PB, Block
from services.cas.store import ContentStore
from tests.unit.services.cas.test_reachability import ALICE, file_node, put, raw

LATER = 3600.0
"""Collections run as if this much later: every block stored by the test is old enough."""


def unpinned_file(store: ContentStore) -> CID:
    """A two-block file stored long ago and pinned by nobody: what a collection takes."""
    leaf = raw(b"a leaf nobody pinned yet")
    node = file_node(leaf)
    root = CID.from_block(node, DAG_PB)
    put(store, Block(root, node), leaf)
    return root


def collect(store: ContentStore) -> list[CID]:
    return store.collect_garbage(grace_s=0, now=time.time() + LATER)


def paused(target: Callable[..., Any], reached: threading.Event, go: threading.Event) -> Any:
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        reached.set()
        assert go.wait(10)
        return target(*args, **kwargs)

    return wrapper


def test_a_collection_between_a_pin_check_and_its_pin_keeps_the_dag(
    store: ContentStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    root = unpinned_file(store)
    checked, go = threading.Event(), threading.Event()
    monkeypatch.setattr(store.pins, "add_all", paused(store.pins.add_all, checked, go))
    pinning = threading.Thread(target=store.pin, args=([root], ALICE))
    pinning.start()
    assert checked.wait(10)
    try:
        assert collect(store) == []
    finally:
        go.set()
        pinning.join()
    assert store.missing_block(root) is None
    assert collect(store) == []


def test_a_pin_made_while_a_collection_marks_is_marked_before_the_delete(
    store: ContentStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The pin lands after the collection's snapshot and before its last phase."""
    root = unpinned_file(store)
    snapshot = store.pins.snapshot
    calls = 0

    def snapshot_then_pin() -> dict[CID, frozenset[str]]:
        nonlocal calls
        calls += 1
        taken = snapshot()
        if calls == 1:
            store.pin([root], ALICE)
        return taken

    monkeypatch.setattr(store.pins, "snapshot", snapshot_then_pin)
    assert collect(store) == []
    assert store.missing_block(root) is None


def test_an_upload_relying_on_a_stored_block_keeps_it_until_it_is_done(
    store: ContentStore,
) -> None:
    """The upload found the leaf stored and wrote only the new root; a collection while it
    streams, or after it committed but before it pinned, must not take the leaf."""
    leaf = raw(b"a leaf stored long ago")
    put(store, leaf)
    node = file_node(leaf)
    root = CID.from_block(node, DAG_PB)
    with store.blocks.stage() as staging:
        staging.add(leaf.cid, leaf.data)
        staging.add(root, node)
        assert collect(store) == []
        staging.commit()
        assert collect(store) == []
        store.pins.add_all({root: len(node) + len(leaf.data)}, ALICE)
    assert store.missing_block(root) is None
    assert collect(store) == []


def test_what_nothing_holds_or_pins_is_still_collected(store: ContentStore) -> None:
    root = unpinned_file(store)
    with store.blocks.hold() as hold:
        assert hold.keep(root)
    assert {cid.multihash for cid in collect(store)} == {
        root.multihash,
        raw(b"a leaf nobody pinned yet").cid.multihash,
    }
