"""A service whose disk fills up, on a real one: a tmpfs of a few MiB mounted as its data
directory. The write that does not fit is a 507 ``insufficient_storage`` (it was a 500
``internal_error``, and a traceback in the log for each request); nothing of it is kept, what
was acknowledged before stays readable, and the service goes on serving, across a restart too.
"""

from __future__ import annotations

import os
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest

from robocloud.cas import Cas
from robocloud.errors import ServerError
from robocloud.identity import Identity
from robocloud.storage import Storage
from robocloud.unixfs import import_bytes
from tests.conftest import ServiceFactory
from tests.integration.services.cas.conftest import store_unchanged
from tests.integration.services.storage.test_ingest_http import approved

QUIET_STORAGE = {
    "ROBOCLOUD_STORAGE_ANCHOR": "false",
    "ROBOCLOUD_KNOWLEDGE_FOLLOW_LEDGER": "false",
    "ROBOCLOUD_STORAGE_PUBLISH_DATASETS": "false",
}


@contextmanager
def small_disk(path: Path, mib: int) -> Iterator[Path]:
    """A tmpfs of ``mib`` MiB at ``path`` until the block ends. Mounting needs root, which CI
    has (it runs Docker): there a refused mount fails the test; elsewhere it skips, saying why.
    """
    path.mkdir()
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={mib}m,mode=0700", "tmpfs", str(path)],
        capture_output=True,
        text=True,
        check=False,
    )
    if mounted.returncode != 0:
        why = f"cannot mount a tmpfs here: {mounted.stderr.strip() or mounted.returncode}"
        if os.environ.get("CI"):
            pytest.fail(why)
        pytest.skip(why)
    try:
        yield path
    finally:
        subprocess.run(["umount", "--lazy", str(path)], check=True)


@pytest.fixture
def disk(tmp_path: Path) -> Iterator[Path]:
    """The service's data directory (its log stays outside, in ``tmp_path``). Asked for
    before ``service_factory``, so the service stops before the disk goes."""
    with small_disk(tmp_path / "disk", 4) as path:
        yield path


def insufficient_storage(raised: pytest.ExceptionInfo[ServerError]) -> None:
    assert (raised.value.status, raised.value.code) == (507, "insufficient_storage")
    assert raised.value.message.startswith("the service's disk is full")


def test_cas_refuses_what_does_not_fit_and_keeps_what_it_had(
    disk: Path, service_factory: ServiceFactory, identity: Identity
) -> None:
    service = service_factory("cas", data_dir=disk)
    with Cas(service.url, identity, retries=0) as cas:
        kept = os.urandom(100_000)
        kept_cid = cas.add_bytes(kept)
        too_large = os.urandom(6_000_000)
        with store_unchanged(service), pytest.raises(ServerError) as refused:
            cas.add_bytes(too_large)
        insufficient_storage(refused)
        assert list((disk / "spool").iterdir()) == []
        _, too_large_cid = import_bytes(too_large)
        assert httpx.get(f"{service.url}/ipfs/{too_large_cid}", timeout=10).status_code == 404
        assert cas.get(kept_cid) == kept
        after = os.urandom(100_000)
        assert cas.get(cas.add_bytes(after)) == after, "the failed upload's space was freed"


def append_until_refused(
    storage: Storage, template: str, identity: Identity, acknowledged: list[str]
) -> None:
    """Append 60 kB records one at a time, each id acknowledged into ``acknowledged``."""
    for t in range(200):
        record = {
            "template": template,
            "robot": identity.address,
            "t": t,
            "topic": "/blob",
            "data": {"text": "a" * 60_000},
        }
        acknowledged += storage.append([record])


def test_storage_keeps_every_acknowledged_record_and_starts_again_on_a_full_disk(
    disk: Path, service_factory: ServiceFactory, identity: Identity
) -> None:
    service = service_factory("storage", QUIET_STORAGE, data_dir=disk)
    acknowledged: list[str] = []
    with Storage(service.url, identity, retries=0) as storage:
        template = approved(storage, {"name": "blob", "version": 1, "fields": {"text": "string"}})
        with pytest.raises(ServerError) as refused:
            append_until_refused(storage, template, identity, acknowledged)
        insufficient_storage(refused)
        assert len(acknowledged) > 10, "the disk held some records first"
        stored = storage.query(template=template, limit=1000).records
        assert [item.id for item in stored] == acknowledged
    service.stop()
    service.start()
    assert httpx.get(f"{service.url}/readyz", timeout=10).json()["status"] == "ready"
    with Storage(service.url, identity, retries=0) as storage:
        stored = storage.query(template=template, limit=1000).records
        assert [item.id for item in stored] == acknowledged
        assert storage.record(acknowledged[-1]).record["data"] == {"text": "a" * 60_000}
