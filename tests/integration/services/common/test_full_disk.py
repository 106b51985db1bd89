"""A service whose disk fills up, on a real one: a tmpfs of a few MiB mounted as its data
directory. The write that does not fit is a 507 ``insufficient_storage`` (it was a 500
``internal_error``, and a traceback in the log for each request); nothing of it is kept, what
was acknowledged before stays readable, and the service goes on serving, across a restart too.

Uploads stop at the disk's reserve (``ROBOCLOUD_DISK_RESERVE_BYTES``), so the robots' other
signed writes, deletions first, still have room; the first tests turn the reserve off to fill
the disk itself.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest

from robocloud.cas import Cas
from robocloud.cid import CID
from robocloud.errors import ServerError
from robocloud.identity import Identity
from robocloud.ingest import Ingest
from robocloud.storage import Storage
from robocloud.unixfs import import_bytes
from tests.bagfactory import START_NS, write_bag
from tests.conftest import ServiceFactory
from tests.integration.services.cas.conftest import multipart, store_unchanged
from tests.integration.services.storage.test_ingest_http import approve, approved

QUIET_STORAGE = {
    "ROBOCLOUD_STORAGE_ANCHOR": "false",
    "ROBOCLOUD_KNOWLEDGE_FOLLOW_LEDGER": "false",
    "ROBOCLOUD_STORAGE_PUBLISH_DATASETS": "false",
}
NO_RESERVE = {"ROBOCLOUD_DISK_RESERVE_BYTES": "0"}
RESERVE = 2 * 1024 * 1024
WITH_RESERVE = {"ROBOCLOUD_DISK_RESERVE_BYTES": str(RESERVE)}


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


@pytest.fixture
def larger_disk(tmp_path: Path) -> Iterator[Path]:
    """Room for a reserve of 2 MiB and writes beside it."""
    with small_disk(tmp_path / "disk", 8) as path:
        yield path


def insufficient_storage(refused: ServerError) -> None:
    assert (refused.status, refused.code) == (507, "insufficient_storage")
    assert refused.message.startswith("the service's disk is full")


def down_to_the_reserve(refused: ServerError, disk: Path) -> None:
    """Refused for the reserve, while the disk still holds about that much free."""
    assert (refused.status, refused.code) == (507, "insufficient_storage")
    assert refused.message.startswith(f"the service keeps {RESERVE} bytes of its disk free")
    assert refused.details["reserve_bytes"] == RESERVE
    assert shutil.disk_usage(disk).free > RESERVE // 2


def test_cas_refuses_what_does_not_fit_and_keeps_what_it_had(
    disk: Path, service_factory: ServiceFactory, identity: Identity
) -> None:
    service = service_factory("cas", NO_RESERVE, data_dir=disk)
    with Cas(service.url, identity, retries=0) as cas:
        kept = os.urandom(100_000)
        kept_cid = cas.add_bytes(kept)
        too_large = os.urandom(6_000_000)
        with store_unchanged(service), pytest.raises(ServerError) as refused:
            cas.add_bytes(too_large)
        insufficient_storage(refused.value)
        assert list((disk / "spool").iterdir()) == []
        _, too_large_cid = import_bytes(too_large)
        assert httpx.get(f"{service.url}/ipfs/{too_large_cid}", timeout=10).status_code == 404
        assert cas.get(kept_cid) == kept
        after = os.urandom(100_000)
        assert cas.get(cas.add_bytes(after)) == after, "the failed upload's space was freed"


def fill_with_records(storage: Storage, identity: Identity) -> tuple[str, list[str], ServerError]:
    """Append 60 kB records to a new template one at a time until one is refused: the
    template, the ids acknowledged (each still stored, in order) and the refusal."""
    template = approved(storage, {"name": "blob", "version": 1, "fields": {"text": "string"}})
    acknowledged: list[str] = []
    for t in range(200):
        record = {
            "template": template,
            "robot": identity.address,
            "t": t,
            "topic": "/blob",
            "data": {"text": "a" * 60_000},
        }
        try:
            acknowledged += storage.append([record])
        except ServerError as error:
            refused = error
            break
    else:
        pytest.fail("the disk took 200 records of 60 kB")
    assert len(acknowledged) > 10, "the disk held some records first"
    stored = storage.query(template=template, limit=1000).records
    assert [item.id for item in stored] == acknowledged
    return template, acknowledged, refused


def test_storage_keeps_every_acknowledged_record_and_starts_again_on_a_full_disk(
    disk: Path, service_factory: ServiceFactory, identity: Identity
) -> None:
    service = service_factory("storage", QUIET_STORAGE | NO_RESERVE, data_dir=disk)
    with Storage(service.url, identity, retries=0) as storage:
        template, acknowledged, refused = fill_with_records(storage, identity)
        insufficient_storage(refused)
    service.stop()
    service.start()
    assert httpx.get(f"{service.url}/readyz", timeout=10).json()["status"] == "ready"
    with Storage(service.url, identity, retries=0) as storage:
        stored = storage.query(template=template, limit=1000).records
        assert [item.id for item in stored] == acknowledged
        assert storage.record(acknowledged[-1]).record["data"] == {"text": "a" * 60_000}


def test_an_ingest_that_fills_the_disk_fails_for_the_disk_and_the_next_one_fits(
    disk: Path, service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    """A bag of 6,000 IMU messages (350 kB) stages more than 4 MiB of records. The job was
    ``ingest_failed`` with the worker's ``OSError`` and the spool's path in its message: the
    robot could not tell its bag's fault from the service's disk."""
    service = service_factory("storage", QUIET_STORAGE | NO_RESERVE, data_dir=disk)
    large = write_bag(tmp_path / "large.bag", "ros1", 6000, start_ns=START_NS)
    small = write_bag(tmp_path / "small.bag", "ros1", 50, start_ns=START_NS)
    with Storage(service.url, identity) as storage, Ingest(service.url, identity) as ingest:
        imu = approve(storage, "sensor_msgs/msg/Imu")
        ingest.bind(imu, msgtype="sensor_msgs/msg/Imu")
        failed = ingest.wait(ingest.upload(large)["id"], timeout_s=120)
        assert failed["status"] == "failed"
        assert failed["error"]["code"] == "insufficient_storage"
        assert failed["error"]["message"].startswith("the service's disk is full (No space")
        assert str(disk) not in failed["error"]["message"]
        assert failed["records"]["committed"] == 0
        assert storage.query(template=imu, limit=10).records == []
        done = ingest.wait(ingest.upload(small)["id"], timeout_s=120)
        assert (done["status"], done["records"]["committed"]) == ("succeeded", 40), done["error"]


def add_until_refused(cas: Cas, added: list[CID]) -> None:
    """Add 400 kB files one at a time, each CID acknowledged into ``added``."""
    for _ in range(30):
        added.append(cas.add_bytes(os.urandom(400_000)))


def test_cas_keeps_its_reserve_so_robots_can_still_free_space(
    larger_disk: Path, service_factory: ServiceFactory, identity: Identity
) -> None:
    """Without the reserve the last upload that fit took the disk's last bytes, and then
    ``pin/rm`` and ``repo/gc`` failed too, on their nonces' journal lines: no robot could free
    space, only the operator."""
    env = WITH_RESERVE | {"ROBOCLOUD_CAS_GC_GRACE_S": "0", "ROBOCLOUD_CAS_GC_INTERVAL_S": "0"}
    service = service_factory("cas", env, data_dir=larger_disk)
    kept = os.urandom(400_000)
    with Cas(service.url, identity, retries=0) as cas:
        added = [cas.add_bytes(kept)]
        with pytest.raises(ServerError) as refused:
            add_until_refused(cas, added)
        down_to_the_reserve(refused.value, larger_disk)
        assert len(added) >= 5, "the disk held some uploads first"
        for cid in added[1:]:
            cas.unpin(cid)
        cas.request("POST", "/api/v0/repo/gc")
        again = os.urandom(400_000)
        assert cas.get(cas.add_bytes(again)) == again
        assert cas.get(added[0]) == kept, "what stayed pinned stayed readable"


def staged_bytes(disk: Path) -> int:
    return sum(pack.stat().st_size for pack in (disk / "packs").glob("*.pack"))


def test_cas_stops_an_upload_when_the_disk_reaches_its_reserve_while_the_body_arrives(
    larger_disk: Path, service_factory: ServiceFactory, identity: Identity
) -> None:
    """The upload's declared length fit when it started; something else (another upload, a
    log) then took the room. The body is refused as soon as the service looks at the disk
    again (every MiB received), before the upload itself fills it, and nothing of it is kept.
    """
    service = service_factory("cas", WITH_RESERVE, data_dir=larger_disk)
    body, content_type = multipart(("late", os.urandom(3 * 1024 * 1024)))
    first = 1024 * 1024 + 100_000
    filler = larger_disk / "filler"

    def arriving() -> Iterator[bytes]:
        yield body[:first]
        deadline = time.monotonic() + 30
        while staged_bytes(larger_disk) == 0:
            assert time.monotonic() < deadline, "the service staged nothing of the first MiB"
            time.sleep(0.01)
        room = shutil.disk_usage(larger_disk).free - RESERVE
        filler.write_bytes(os.urandom(room + 128 * 1024))
        yield from (body[at : at + 64 * 1024] for at in range(first, len(body), 64 * 1024))

    with Cas(service.url, identity, retries=0) as cas:
        with store_unchanged(service), pytest.raises(ServerError) as refused:
            cas.request(
                "POST",
                "/api/v0/add",
                content=arriving(),
                content_sha256=hashlib.sha256(body).hexdigest(),
                headers={"Content-Type": content_type, "Content-Length": str(len(body))},
            )
        down_to_the_reserve(refused.value, larger_disk)
        assert "declared_bytes" not in refused.value.details
        assert staged_bytes(larger_disk) == 0
        filler.unlink()
        after = os.urandom(100_000)
        assert cas.get(cas.add_bytes(after)) == after


def test_storage_refuses_records_at_its_reserve_and_still_takes_other_signed_writes(
    larger_disk: Path, service_factory: ServiceFactory, identity: Identity
) -> None:
    service = service_factory("storage", QUIET_STORAGE | WITH_RESERVE, data_dir=larger_disk)
    with Storage(service.url, identity, retries=0) as storage:
        _, _, refused = fill_with_records(storage, identity)
        down_to_the_reserve(refused, larger_disk)
        other = approved(storage, {"name": "note", "version": 1, "fields": {"text": "string"}})
        assert storage.get_json(f"/v1/templates/{other}")["status"] == "approved"


def stored_ids(storage: Storage, template: str) -> list[str]:
    ids: list[str] = []
    cursor = None
    while True:
        page = storage.query(template=template, limit=1000, cursor=cursor)
        ids += [item.id for item in page.records]
        if (cursor := page.next) is None:
            return ids


@pytest.mark.parametrize(("room_mib", "stopped_while"), [(4, "staging"), (10, "committing")])
def test_an_ingest_job_stops_at_the_reserve_and_goes_on_once_space_is_freed(
    room_mib: int,
    stopped_while: str,
    service_factory: ServiceFactory,
    identity: Identity,
    tmp_path: Path,
) -> None:
    """The bag (350 kB) passes the request's check; its job then writes 40 times that at its
    peak (spool, records, indexes, logs), which took the disk's last bytes behind the
    reserve's back. It stops at the reserve instead, staging or committing (one batch of 250
    records past it, at most), and once space is freed the robot sends the bag again or
    resumes the job, whose committed records stay."""
    env = QUIET_STORAGE | WITH_RESERVE
    env |= {
        "ROBOCLOUD_STORAGE_INGEST_BATCH_RECORDS": "250",
        "ROBOCLOUD_STORAGE_SEGMENT_RECORDS": "250",
    }
    bag = write_bag(tmp_path / "large.bag", "ros1", 6000, start_ns=START_NS)
    with small_disk(tmp_path / "disk", 32) as disk:
        service = service_factory("storage", env, data_dir=disk)
        filler = disk / "filler"
        with Storage(service.url, identity) as storage, Ingest(service.url, identity) as ingest:
            imu = approve(storage, "sensor_msgs/msg/Imu")
            ingest.bind(imu, msgtype="sensor_msgs/msg/Imu")
            filler.write_bytes(bytes(shutil.disk_usage(disk).free - RESERVE - (room_mib << 20)))
            failed = ingest.wait(ingest.upload(bag)["id"], timeout_s=120)
            assert failed["status"] == "failed"
            error = failed["error"]
            assert error["code"] == "insufficient_storage"
            assert error["message"].startswith(f"the service keeps {RESERVE} bytes of its disk")
            assert error["details"]["reserve_bytes"] == RESERVE
            assert shutil.disk_usage(disk).free > RESERVE // 2
            committed = failed["records"]["committed"]
            kept = stored_ids(storage, imu)
            assert len(kept) == committed
            filler.unlink()
            if stopped_while == "staging":
                assert (error["resumable"], committed) == (False, 0)
                done = ingest.wait(ingest.upload(bag)["id"], timeout_s=120)
            else:
                assert error["resumable"]
                assert 0 < committed < 4800
                done = ingest.wait(ingest.resume(failed["id"])["id"], timeout_s=120)
            assert (done["status"], done["records"]["committed"]) == ("succeeded", 4800), done
            ids = stored_ids(storage, imu)
            assert (len(set(ids)), ids[:committed]) == (4800, kept)
        service.stop()
