"""A record store over real logs and a real catalog in a temporary directory."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from services.storage.catalog import Catalog
from services.storage.recordlog import RecordLogs
from services.storage.recordstore import Authorship, RecordStore

ROBOT_A = "0x90F8bf6A479f320ead074411a4B0e7944Ea8c9C1"
ROBOT_B = "0xFFcf8FDEE72ac11b5c542428B35EEF5769C409f0"
REVIEWER = "0x22d491Bde2303f2f43325b2108D26f1eAbA1e32b"
AUTHOR = Authorship(
    signer=ROBOT_A,
    audience="storage@local",
    method="POST",
    path="/v1/records",
    query="",
    timestamp=1_700_000_000,
    nonce="n" * 16,
    content_sha256="0" * 64,
    signature="0x" + "1" * 130,
    request_sha256="2" * 64,
    received_at_ns=1,
)
STATE = {
    "name": "state",
    "fields": {
        "mode": "string",
        "speed": "float",
        "count": "int",
        "docked": "bool",
        "pose": {"container": {"x": "float", "y": "float"}},
        "ranges": {"array": "float"},
    },
}


def approve(catalog: Catalog, document: dict[str, Any]) -> str:
    version = catalog.create(document, author=ROBOT_A)
    catalog.submit(version.id, author=ROBOT_A)
    catalog.review(version.id, "approve", reviewer=REVIEWER)
    return version.id


def state_record(
    t: int, *, robot: str = ROBOT_A, mode: str = "idle", **data: Any
) -> dict[str, Any]:
    values: dict[str, Any] = {
        "mode": mode,
        "speed": t / 10,
        "count": t % 7,
        "docked": mode == "docked",
        "pose": {"x": float(t), "y": -1.5},
        "ranges": [0.5, 1.5],
    }
    values.update(data)
    return {"template": "state@1", "topic": "/state", "robot": robot, "t": t, "data": values}


StoreFactory = Callable[[], RecordStore]


@pytest.fixture
def open_store(tmp_path: Path) -> Iterator[StoreFactory]:
    """Open (or reopen) the store in ``tmp_path``; everything opened is closed at the end."""
    opened: list[tuple[RecordStore, RecordLogs, Catalog]] = []

    def factory() -> RecordStore:
        for store, logs, catalog in opened:
            store.close()
            logs.close()
            catalog.close()
        opened.clear()
        catalog = Catalog(tmp_path / "catalog")
        if not catalog.list():
            approve(catalog, STATE)
        logs = RecordLogs(tmp_path / "logs")
        store = RecordStore(
            tmp_path, logs, catalog, segment_records=16, segment_cache=4, array_inline_bytes=256
        )
        opened.append((store, logs, catalog))
        return store

    yield factory
    for store, logs, catalog in opened:
        store.close()
        logs.close()
        catalog.close()
