"""Ingest of a ROS 2 bag *directory* named by its CID in cas, through real cas and storage
processes: a split recording gives the records its storage files give when uploaded as
streams; a directory that is not a bag, too large, or not in cas is refused with nothing stored.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from robocloud.cas import Cas
from robocloud.cid import CID
from robocloud.dagpb import Link
from robocloud.directory import directory_node
from robocloud.errors import ApiError
from robocloud.identity import Identity
from robocloud.ingest import Ingest
from robocloud.storage import Storage
from robocloud.templates import canonical_record
from robocloud.unixfs import ImportParams, import_bytes
from services.storage.matcher import draft_template
from tests.bagfactory import TOPICS, typestore_for, write_bag, write_split_bag
from tests.conftest import ServiceFactory
from tests.procs import SHARED_DATA, ServiceProcess

SPLIT = SHARED_DATA / "rosbag2" / "rosbag2_wbag_sqlite3"
"""rosbag2's own split fixture: 5 ``.db3`` files, 8 ``std_msgs/String`` topics, 6,074 messages;
its ``metadata.yaml`` times disagree with the stored ones (SOURCES.md)."""
QUIET = {
    "ROBOCLOUD_STORAGE_ANCHOR": "false",
    "ROBOCLOUD_STORAGE_PUBLISH_DATASETS": "false",
    "ROBOCLOUD_LOG_LEVEL": "WARNING",
}


@dataclass
class Node:
    storage: ServiceProcess
    cas: Cas
    ingest: Ingest
    records: Storage


@pytest.fixture
def node(service_factory: ServiceFactory, identity: Identity) -> Iterator[Node]:
    cas = service_factory("cas")
    storage = service_factory(
        "storage",
        {
            **QUIET,
            "ROBOCLOUD_CAS_URL": cas.url,
            "ROBOCLOUD_STORAGE_MAX_BAG_BYTES": "4000000",
            "ROBOCLOUD_STORAGE_MAX_BAG_ENTRIES": "6",
        },
    )
    with (
        Cas(cas.url, identity) as client,
        Ingest(storage.url, identity) as ingest,
        Storage(storage.url, identity) as records,
    ):
        yield Node(storage, client, ingest, records)


def approve_and_bind(node: Node, msgtype: str) -> str:
    document = draft_template(typestore_for("sqlite3"), msgtype)
    created = node.records.create_template(document)
    node.records.submit_template(created.id)
    node.records.review_template(created.id, "approve", "test")
    node.ingest.bind(created.id, msgtype=msgtype)
    return created.id


def ingested(node: Node, job: dict[str, Any]) -> list[dict[str, Any]]:
    """The records a job committed, per template in log order, read back from the node."""
    done = node.ingest.wait(job["id"], timeout_s=300)
    assert done["status"] == "succeeded", done["error"]
    assert done["records"]["committed"] == done["messages"]["total"] > 0
    kept = node.storage.data_dir / "ingest" / done["id"]
    # A save of job.json may be under way (its temporary file beside it) as the job is read.
    left = [path.name for path in kept.iterdir() if not path.name.startswith(".job.json.")]
    assert left == ["job.json"], "the bag was not removed"
    records = []
    for template, (first, last) in sorted(done["record_ids"].items()):
        start, stop = int(first.rsplit("-", 1)[1]), int(last.rsplit("-", 1)[1]) + 1
        for index in range(start, stop):
            stored = node.records.record(f"{template.replace('@', '-')}-{index}")
            records.append(stored.record)
    return records


def ordered(records: list[dict[str, Any]]) -> list[bytes]:
    """Records as canonical bytes, sorted: split files may share a timestamp at their seam,
    and which of two equal-time messages comes first is the reader's choice."""
    return sorted(canonical_record(record) for record in records)


def test_a_real_split_recording_by_directory_cid(node: Node) -> None:
    template = approve_and_bind(node, "std_msgs/msg/String")
    directory = node.cas.add_directory(SPLIT)
    by_cid = ingested(node, node.ingest.from_cas(directory))
    assert len(by_cid) == 6074
    assert {record["topic"] for record in by_cid} == {f"/{name * 3}" for name in "ABCDEFGH"}
    assert {record["template"] for record in by_cid} == {template}
    times = [record["t"] for record in by_cid]
    assert (min(times), max(times)) == (1000, 2998)

    streamed: list[dict[str, Any]] = []
    for part in sorted(SPLIT.glob("*.db3")):
        streamed.extend(ingested(node, node.ingest.upload(part)))
    assert ordered(by_cid) == ordered(streamed)


@pytest.mark.parametrize("kind", ["sqlite3", "mcap"])
def test_a_generated_split_bag_by_directory_cid(node: Node, tmp_path: Path, kind: str) -> None:
    """Images included: their bytes go to cas and both ingests hold the same CIDs."""
    for msgtype in TOPICS.values():
        approve_and_bind(node, msgtype)
    split = write_split_bag(tmp_path / "split", kind, 600, 4)  # type: ignore[arg-type]
    whole = write_bag(tmp_path / "whole", "mcap", 600)
    by_cid = ingested(node, node.ingest.from_cas(node.cas.add_directory(split)))
    streamed = ingested(node, node.ingest.upload(next(whole.glob("*.mcap"))))
    assert len(by_cid) == 600
    assert ordered(by_cid) == ordered(streamed)
    image = next(r for r in by_cid if r["topic"] == "/camera/image_raw")["data"]["data"]
    assert len(node.cas.get(image)) == 8 * 6 * 3


def refused(node: Node, cid: CID | str) -> ApiError:
    """The node refuses ``cid`` at once, and nothing of it stays: no job, no record, no file."""
    with pytest.raises(ApiError) as caught:
        node.ingest.from_cas(cid)
    incoming = node.storage.data_dir / "ingest" / "incoming"
    assert not incoming.exists() or list(incoming.iterdir()) == []
    kept = {p.name for p in (node.storage.data_dir / "ingest").iterdir()}
    assert kept <= {"incoming", "ingested.sqlite"}, "no job"
    assert node.records.query(topic="/AAA").records == []
    return caught.value


def test_a_bag_file_uploaded_then_sent_by_its_cids_is_ingested_once(
    node: Node, tmp_path: Path
) -> None:
    """The robot uploads run.bag, then ingests it again by the CID ``robocloud put`` gave
    it and by a CIDv0 of it: one bag, so its IMU records are stored once (they were three
    times: each way was a bag of its own)."""
    imu = approve_and_bind(node, "sensor_msgs/msg/Imu")
    bag = write_bag(tmp_path / "run.bag", "ros1", 50)
    first = node.ingest.wait(node.ingest.upload(bag)["id"], timeout_s=120)
    assert first["records"]["committed"] == 40, first["error"]
    cids = [
        node.cas.add_file(bag),
        node.cas.add_file(bag, params=ImportParams(cid_version=0, raw_leaves=False)),
    ]
    assert len({str(cid) for cid in cids}) == 2
    for cid in cids:
        again = node.ingest.wait(node.ingest.from_cas(cid)["id"], timeout_s=120)
        assert (again["status"], again["bag"]) == ("succeeded", f"cid:{cid}"), again["error"]
        assert again["records"]["committed"] == 0
        (imu_topic,) = [topic for topic in again["topics"] if topic["template"] == imu]
        assert imu_topic["ingested_by"] == first["id"]
    assert len(node.records.query(template=imu, limit=100).records) == 40


def test_directories_that_are_not_bags_are_refused(node: Node, tmp_path: Path) -> None:
    approve_and_bind(node, "std_msgs/msg/String")
    no_metadata = tmp_path / "no_metadata"
    shutil.copytree(SPLIT, no_metadata)
    (no_metadata / "metadata.yaml").unlink()
    cid = node.cas.add_directory(no_metadata)
    error = refused(node, cid)
    assert (error.status, error.code) == (400, "invalid_bag")
    assert error.details == {"cid": str(cid), "reason": "missing_metadata"}
    assert "metadata.yaml" in error.message

    nested = tmp_path / "nested"
    shutil.copytree(SPLIT, nested / "inner")
    (nested / "metadata.yaml").write_bytes((SPLIT / "metadata.yaml").read_bytes())
    error = refused(node, node.cas.add_directory(nested))
    assert (error.status, error.code) == (400, "invalid_bag")
    assert (error.details["reason"], error.details["entry"]) == ("not_a_file", "inner")

    crowded = tmp_path / "crowded"
    shutil.copytree(SPLIT, crowded)
    (crowded / "notes.txt").write_text("a seventh entry\n")
    error = refused(node, node.cas.add_directory(crowded))
    assert (error.status, error.code) == (400, "invalid_bag")
    assert error.details["reason"] == "too_many_entries"


def test_a_directory_over_the_size_bound_is_refused(node: Node, tmp_path: Path) -> None:
    approve_and_bind(node, "std_msgs/msg/String")
    large = tmp_path / "large"
    shutil.copytree(SPLIT, large)
    with (large / "wbag_4.db3").open("ab") as part:
        part.write(bytes(4_000_000))
    cid = node.cas.add_directory(large)
    error = refused(node, cid)
    assert (error.status, error.code) == (413, "payload_too_large")
    assert error.details == {"cid": str(cid), "limit": 4_000_000}


def test_a_cid_not_in_cas_is_refused(node: Node) -> None:
    """Neither the directory nor its one file was ever stored: the CIDs are computed here."""
    _, metadata = import_bytes((SPLIT / "metadata.yaml").read_bytes())
    _, directory = directory_node([Link(metadata, "metadata.yaml", 1690)])
    for cid in (metadata, directory.cid):
        error = refused(node, cid)
        assert (error.status, error.code) == (404, "bag_not_found")
        assert error.details == {"cid": str(cid)}
