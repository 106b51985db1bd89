"""Ingest jobs against the real record store: records as the bag holds them, unbound topics
reported, failures leaving the logs untouched, and an interrupted commit settled exactly once."""

from __future__ import annotations

import errno
import json
import math
import shutil
import time
import tracemalloc
from collections.abc import Iterator, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Rosbag1Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from robocloud.identity import Identity
from robocloud.templates import parse_template
from robocloud.unixfs import import_bytes
from services.storage import ingest
from services.storage.bags import Bag
from services.storage.catalog import Catalog
from services.storage.ingest import IngestJobs, Job, JobNotFound, TooManyJobs
from services.storage.matcher import Bindings, draft_template
from services.storage.recordlog import RecordLogs
from services.storage.recordstore import ArrayOffload, Authorship, RecordStore, record_id
from services.storage.staging import (
    BLOB_BATCH_BYTES,
    BLOB_BATCH_COUNT,
    CasBlobs,
    SpoolWriter,
    compile_plan,
    stage_window,
)
from tests.bagfactory import (
    FRAME_BYTES,
    START_NS,
    TOPICS,
    BagKind,
    camera_run,
    ros2_mcap,
    typestore_for,
    write_bag,
    write_flags_bag,
    write_messages,
)
from tests.bagfactory import imu as imu_message
from tests.blobs import MemoryBlobs
from tests.procs import SHARED_DATA
from tests.waiting import wait_for


class Node:
    def __init__(
        self,
        root: Path,
        segment_records: int = 4096,
        publish: ingest.Publish | None = None,
    ) -> None:
        self.root = root
        self.publish = publish
        self.author = Identity.generate().address
        self.catalog = Catalog(root / "catalog")
        self.logs = RecordLogs(root / "logs")
        self.store = RecordStore(root, self.logs, self.catalog, segment_records=segment_records)
        self.bindings = Bindings(root / "bindings.json")
        self.blobs = MemoryBlobs()
        self.jobs = self.open_jobs()

    def open_jobs(
        self, batch_records: int = 50, staging_workers: int = 1, **options: Any
    ) -> IngestJobs:
        """Jobs that stage any bag in ``staging_workers`` processes, each a window of it;
        ``options`` are IngestJobs' other keywords."""
        return IngestJobs(
            self.root / "jobs",
            self.store,
            self.logs,
            self.bindings,
            lambda: self.blobs.put_many,
            batch_records=batch_records,
            staging_workers=staging_workers,
            parallel_from_messages=0,
            publish=self.publish,
            **options,
        )

    def stage_in(self, workers: int) -> None:
        self.jobs.close()
        self.jobs = self.open_jobs(staging_workers=workers)

    def approve(self, msgtype: str) -> str:
        return self.approved(draft_template(typestore_for("sqlite3"), msgtype))

    def approved(self, document: dict[str, Any]) -> str:
        """The id of ``document`` created, submitted and approved by this node's author."""
        version = self.catalog.create(document, author=self.author)
        self.catalog.submit(version.id, author=self.author)
        self.catalog.review(version.id, "approve", reviewer=self.author)
        return version.id

    def close(self) -> None:
        self.jobs.close()
        self.store.close()
        self.logs.close()
        self.catalog.close()


@pytest.fixture
def node(tmp_path: Path) -> Iterator[Node]:
    created = Node(tmp_path / "node")
    yield created
    created.close()


def authorship(nonce: str = "nonce-000000000000") -> Authorship:
    return Authorship(
        signer=Identity.generate().address,
        audience="storage@local",
        method="POST",
        path="/v1/ingest",
        query="",
        timestamp=1,
        nonce=nonce,
        content_sha256="0" * 64,
        signature="0x" + "0" * 130,
        request_sha256="1" * 64,
        received_at_ns=1,
    )


def bag(tmp_path: Path, name: str, count: int, kind: str = "sqlite3") -> Path:
    path = tmp_path / name
    return write_bag(path, kind, count, start_ns=START_NS)  # type: ignore[arg-type]


def test_ingest_writes_bound_topics_and_reports_the_rest(node: Node, tmp_path: Path) -> None:
    imu = node.approve("sensor_msgs/msg/Imu")
    image = node.approve("sensor_msgs/msg/Image")
    node.bindings.bind(template_id=imu, msgtype="sensor_msgs/msg/Imu")
    node.bindings.bind(template_id=image, topic="/camera/image_raw")
    author = authorship()
    job = node.jobs.wait(node.jobs.submit(bag(tmp_path, "b", 200), "upload:x", author).id, 60)
    assert job.status == "succeeded", job.error
    assert (job.messages_done, job.messages_total) == (180, 180)
    assert job.records_committed == 180
    reports = {t.topic: t for t in job.topics}
    assert reports["/gps"].template is None
    assert "no template" in (reports["/gps"].skipped or "")
    assert job.to_json()["unbound_topics"] == ["/gps"]
    draft = reports["/gps"].draft
    assert draft is not None
    assert draft["name"] == "nav_sat_fix"
    assert parse_template(draft).id == "nav_sat_fix@1"
    assert reports["/imu"].draft is None
    assert node.logs.size(imu) == 160
    assert node.logs.size(image) == 20
    first = node.store.get("imu-1-0")
    assert first.record["t"] == START_NS
    assert first.record["robot"] == author.signer
    assert first.record["data"]["frame_id"] == "imu_link"
    assert first.meta["nonce"] == author.nonce
    frame = node.store.get("image-1-0").record["data"]["data"]
    assert node.blobs.files[frame][:3] == bytes([9, 10, 11])
    assert job.record_ids == {imu: ["imu-1-0", "imu-1-159"], image: ["image-1-0", "image-1-19"]}
    assert [path.name for path in (node.root / "jobs" / job.id).iterdir()] == ["job.json"]


def test_an_unbound_topic_names_the_approved_templates_its_draft_fits(
    node: Node, tmp_path: Path
) -> None:
    """A topic bound to no template (an IMU on a second topic, bound by topic only) had its
    draft alone, whose ``templates create`` is a 409 since the name is taken: the approved
    template with the same fields, which it can be bound to as it is, went unsaid."""
    imu = node.approve("sensor_msgs/msg/Imu")
    gps = node.approve("sensor_msgs/msg/NavSatFix")
    node.bindings.bind(template_id=gps, topic="/gps")
    same_fields = draft_template(typestore_for("sqlite3"), "sensor_msgs/msg/Imu")
    node.catalog.create({**same_fields, "name": "imu_draft"}, author=node.author)
    job = node.jobs.wait(node.jobs.submit(bag(tmp_path, "b", 200), "upload:x", authorship()).id, 60)
    assert job.status == "succeeded", job.error
    fits = {report.topic: report.fits for report in job.topics}
    assert fits == {"/imu": [imu], "/gps": [], "/camera/image_raw": []}
    assert job.to_json()["topics"][0]["fits"] == [imu]
    reopened = Catalog(Path(shutil.copytree(node.root / "catalog", tmp_path / "catalog")))
    try:
        assert reopened.approved_like(node.catalog.get(imu).template) == [imu]
    finally:
        reopened.close()


def test_a_topic_whose_name_no_record_holds_is_skipped_alone(node: Node, tmp_path: Path) -> None:
    """A topic named with a space, a letter outside ASCII or past 256 characters, bound by
    its type, failed the whole job (record_invalid "at t=0"), every other topic with it."""
    imu = node.approve("sensor_msgs/msg/Imu")
    node.bindings.bind(template_id=imu, msgtype="sensor_msgs/msg/Imu")
    store = get_typestore(Stores.ROS1_NOETIC)
    topics = ["/ok", "/with space", "/\u00fcn\u00ef", "/" + "a" * 300]
    path = tmp_path / "names.bag"
    with Rosbag1Writer(path) as writer:
        for index, topic in enumerate(topics):
            connection = writer.add_connection(topic, "sensor_msgs/msg/Imu", typestore=store)
            raw = store.serialize_ros1(imu_message(store, index, START_NS), "sensor_msgs/msg/Imu")
            writer.write(connection, START_NS + index, raw)
    job = node.jobs.wait(node.jobs.submit(path, "upload:names", authorship()).id, 60)
    assert job.status == "succeeded", job.error
    assert {report.topic: report.skipped or report.template for report in job.topics} == {
        "/ok": imu,
        **{topic: ingest.UNRECORDABLE_TOPIC for topic in topics[1:]},
    }
    assert job.records_committed == 1
    assert node.store.get("imu-1-0").record["topic"] == "/ok"


def test_a_tf_bag_s_frame_ids_are_found_by_keyword(node: Node, tmp_path: Path) -> None:
    """A TF message's strings are all inside its array of transforms, and keyword search
    found none of them. Its template's spool now has a keyword line a record, and the
    commit hands those texts to the index (evo's TF recording of shared/data)."""
    recording = SHARED_DATA / "rosbag1" / "evo_tf_example.bag"
    holding: dict[str, int] = {}
    with AnyReader([recording]) as reader:
        for connection, _, raw in reader.messages():
            message = reader.deserialize(raw, connection.msgtype)
            for frame in {t.header.frame_id for t in message.transforms} | {
                t.child_frame_id for t in message.transforms
            }:
                holding[frame] = holding.get(frame, 0) + 1
    with Bag.open(recording) as bag:
        [typestore] = {connection.typestore for connection in bag.connections}
    tfm = "tf2_msgs/msg/TFMessage"
    version_id = node.approved(draft_template(typestore, tfm))
    node.bindings.bind(template_id=version_id, msgtype=tfm)
    bag_copy = Path(shutil.copy(recording, tmp_path / "tf.bag"))
    job = node.jobs.wait(node.jobs.submit(bag_copy, "upload:tf", authorship()).id, 60)
    assert (job.status, job.records_committed) == ("succeeded", 518), job.error
    node.store.index_keywords()
    assert {"base_link", "odom"} <= holding.keys()
    for frame, count in holding.items():
        found = node.store.keywords.search([frame.lower()], version_id)[version_id]
        assert len(found) == count, frame
        record = node.store.get(f"tf_message-1-{min(found)}").record["data"]
        frames = {t["child_frame_id"] for t in record["transforms"]}
        assert frame in frames | {t["header"]["frame_id"] for t in record["transforms"]}, frame


def test_recorded_service_calls_are_drafted_and_ingested(node: Node, tmp_path: Path) -> None:
    """A service's introspection events, recorded with the service's definition, had no
    draft and no records; drafted and bound, each call becomes a record."""
    path = Path(shutil.copy(SHARED_DATA / "mcap/rosbag2_cpp_topics_and_services.mcap", tmp_path))
    first = node.jobs.wait(node.jobs.submit(path, "upload:s", authorship()).id, 60)
    [report] = [t for t in first.topics if t.topic == "/add_two_ints/_service_event"]
    assert report.skipped == "no template is bound to this topic or message type"
    assert report.draft is not None
    assert report.draft["fields"]["request"] == {"array": {"container": {"a": "int", "b": "int"}}}
    version_id = node.approved(report.draft)
    node.bindings.bind(template_id=version_id, msgtype="example_interfaces/srv/AddTwoInts_Event")
    path = Path(shutil.copy(SHARED_DATA / "mcap/rosbag2_cpp_topics_and_services.mcap", tmp_path))
    job = node.jobs.wait(node.jobs.submit(path, "upload:s2", authorship("nonce-1")).id, 60)
    assert (job.status, job.records_committed) == ("succeeded", 6), job.error
    calls = [node.store.get(f"add_two_ints_event-1-{n}").record["data"] for n in range(6)]
    assert [c["request"] or c["response"] for c in calls] == [
        [{"a": 1, "b": 3}],
        [{"sum": 4}],
        [{"a": 2, "b": 3}],
        [{"sum": 5}],
        [{"a": 3, "b": 3}],
        [{"sum": 6}],
    ]


def test_an_unbound_topic_that_cannot_be_decoded_says_why(node: Node, tmp_path: Path) -> None:
    """Such a topic has no draft, and binding it would fail the job: the report said only
    that no template was bound, as for any topic."""
    path = Path(
        shutil.copytree(
            SHARED_DATA / "rosbag2/rosbag2_topics_and_service_events_sqlite3", tmp_path / "bag"
        )
    )
    job = node.jobs.wait(node.jobs.submit(path, "upload:u", authorship()).id, 60)
    assert job.status == "succeeded", job.error
    reports = {t.topic: t for t in job.topics}
    assert reports["/test_service1/_service_event"].skipped == (
        "no template is bound to this topic or message type, and its type cannot be decoded: "
        "the bag carries no definition of test_msgs/srv/BasicTypes_Event and rosbags' "
        "ros2_humble typestore has none either"
    )
    assert reports["/test_service1/_service_event"].draft is None
    assert reports["/test_topic1"].skipped == "no template is bound to this topic or message type"


def test_a_type_holding_itself_is_one_topic_skipped_not_a_failed_job(
    node: Node, tmp_path: Path
) -> None:
    """A 300-byte bag whose one definition holds itself failed its job whole with
    ``RecursionError``, its good topic with it."""
    text = node.approve("std_msgs/msg/String")
    node.bindings.bind(template_id=text, msgtype="std_msgs/msg/String")
    path = ros2_mcap(
        tmp_path / "loop.mcap",
        ("/loop", "pkg/msg/Foo", "pkg/Foo[] children\n", bytes(8)),
        ("/ok", "std_msgs/msg/String", "string data\n", b"\x00\x01\x00\x00\x03\x00\x00\x00hi\x00"),
    )
    job = node.jobs.wait(node.jobs.submit(path, "upload:loop", authorship()).id, 60)
    assert (job.status, job.records_committed) == ("succeeded", 1), job.error
    [loop] = [report for report in job.topics if report.topic == "/loop"]
    assert loop.skipped == (
        "no template is bound to this topic or message type, and its type cannot be decoded: "
        "the bag's definition has a type holding itself (pkg/msg/Foo -> pkg/msg/Foo): "
        "no ROS message can"
    )
    assert node.store.get("string-1-0").record["data"] == {"data": "hi"}


def test_distinct_drafts_of_one_name_are_named_apart(node: Node, tmp_path: Path) -> None:
    """A draft is named after its type's last part: ``sensor_msgs/msg/Imu`` and
    ``my_msgs/msg/Imu`` both drafted ``imu``, and ``--drafts`` (one file a name) kept one.
    Two topics of one type still share one draft."""
    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg("float64 level", "my_msgs/msg/Imu"))
    path = tmp_path / "imus.bag"
    with Rosbag1Writer(path) as writer:
        for topic, msgtype in [
            ("/imu", "sensor_msgs/msg/Imu"),
            ("/my_imu", "my_msgs/msg/Imu"),
            ("/imu_back", "sensor_msgs/msg/Imu"),
        ]:
            connection = writer.add_connection(topic, msgtype, typestore=store)
            message = (
                store.types[msgtype](level=0.5)
                if msgtype.startswith("my")
                else imu_message(store, 0, START_NS)
            )
            writer.write(connection, START_NS, store.serialize_ros1(message, msgtype))
    job = node.jobs.wait(node.jobs.submit(path, "upload:imus", authorship()).id, 60)
    assert job.status == "succeeded", job.error
    drafts = {report.topic: report.draft for report in job.topics}
    assert {topic: draft and draft["name"] for topic, draft in drafts.items()} == {
        "/imu": "imu",
        "/my_imu": "imu_2",
        "/imu_back": "imu",
    }
    assert drafts["/imu"] == drafts["/imu_back"] == draft_template(store, "sensor_msgs/msg/Imu")
    my_imu = drafts["/my_imu"]
    assert my_imu is not None
    assert my_imu["fields"] == {"level": "float"}
    assert parse_template(my_imu).id == "imu_2@1"


def test_a_bag_on_its_way_in_leaves_nothing_behind(node: Node, tmp_path: Path) -> None:
    """Each accepted upload left its empty spool directory in ``incoming/``, and one refused
    with too_many_jobs after it arrived left the whole bag."""
    incoming = node.root / "jobs" / "incoming"
    source = bag(tmp_path, "b.bag", 20, kind="ros1")
    with node.jobs.incoming() as spool:
        accepted = Path(shutil.copy(source, spool / "bag.bag"))
        job = node.jobs.submit(accepted, "upload:a", authorship())
    assert list(incoming.iterdir()) == []
    assert node.jobs.wait(job.id, 60).status == "succeeded"
    node.jobs.max_pending = 0
    with node.jobs.incoming() as spool:
        refused = Path(shutil.copy(source, spool / "bag.bag"))
        with pytest.raises(TooManyJobs):
            node.jobs.submit(refused, "upload:r", authorship("nonce-111111111111"))
    assert list(incoming.iterdir()) == []
    assert sorted(path.name for path in (node.root / "jobs").iterdir()) == [
        job.id,
        "incoming",
        "ingested.sqlite",
    ]


def test_one_robot_holds_its_share_of_the_queue_and_the_rest_is_for_others(
    node: Node, tmp_path: Path
) -> None:
    """Before, one robot's bags could hold every place and refuse every other robot's."""
    node.jobs.close()
    node.jobs = node.open_jobs(max_pending=3, max_pending_per_robot=2)
    node.jobs.close()  # its worker ends: what is submitted stays queued
    greedy, other = authorship(), authorship()
    source = bag(tmp_path, "b.bag", 20, kind="ros1")
    queued = [
        node.jobs.submit(Path(shutil.copy(source, tmp_path / f"{n}.bag")), f"upload:g{n}", greedy)
        for n in range(2)
    ]
    with pytest.raises(TooManyJobs) as robot_full:
        node.jobs.admit(greedy.signer.lower())
    assert (robot_full.value.limit, robot_full.value.per) == (2, "robot")
    assert str(robot_full.value).startswith("this robot has 2 ingest jobs queued or running")
    node.jobs.admit(other.signer)
    queued.append(
        node.jobs.submit(Path(shutil.copy(source, tmp_path / "o.bag")), "upload:o", other)
    )
    with pytest.raises(TooManyJobs) as service_full:
        node.jobs.admit(authorship().signer)
    assert (service_full.value.limit, service_full.value.per) == (3, "service")
    assert [node.jobs.get(job.id).status for job in queued] == ["queued"] * 3


def test_a_bag_left_on_its_way_in_by_a_crash_is_removed_at_open(node: Node) -> None:
    incoming = node.root / "jobs" / "incoming"
    (incoming / ".bag-torn").mkdir(parents=True)
    (incoming / ".bag-torn" / "upload").write_bytes(b"#ROSBAG V2.0\n")
    node.jobs.close()
    node.jobs = node.open_jobs()
    assert not incoming.exists()


WORKERS = pytest.mark.parametrize("workers", [1, 3], ids=["1-process", "3-processes"])


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_staging_in_processes_logs_what_one_pass_logs(tmp_path: Path, kind: str) -> None:
    """Time windows staged by three processes give the logs, byte for byte and in the same
    order, that one process staging the whole bag gives; their frames reach the blob sink."""
    logs: dict[int, dict[str, list[bytes]]] = {}
    author = authorship()
    for workers in (1, 3):
        node = Node(tmp_path / f"node-{workers}")
        try:
            node.stage_in(workers)
            imu = node.approve("sensor_msgs/msg/Imu")
            image = node.approve("sensor_msgs/msg/Image")
            node.bindings.bind(template_id=imu, msgtype="sensor_msgs/msg/Imu")
            node.bindings.bind(template_id=image, msgtype="sensor_msgs/msg/Image")
            folder = tmp_path / f"bag-{workers}"
            folder.mkdir()
            path = bag(folder, "b.bag" if kind == "ros1" else "b", 300, kind=kind)
            job = node.jobs.wait(node.jobs.submit(path, "upload:p", author).id, 60)
            assert job.status == "succeeded", job.error
            assert (job.messages_done, job.records_committed) == (270, 270)
            logs[workers] = {
                template_id: [e.record for e in node.logs.entries(template_id, 0, 270)]
                for template_id in (imu, image)
            }
            frames = [json.loads(record)["data"]["data"] for record in logs[workers][image]]
            assert len(frames) == 30
            assert set(frames) <= set(node.blobs.files)
            assert node.blobs.files[frames[0]][:3] == bytes([9, 10, 11])
        finally:
            node.close()
    assert [len(records) for records in logs[3].values()] == [240, 30]
    assert logs[3] == logs[1]


def test_ingested_views_are_those_live_appends_build(tmp_path: Path) -> None:
    """An ingest writes segments from the documents its staging prepared, never parsing a
    record; the same records appended live (each parsed and flattened) give the same segment
    files, indexes, manifest and tail, byte for byte. The second bag finds a tail left by the
    first, which it completes before writing whole segments."""
    author = authorship()
    ingested = Node(tmp_path / "ingested", segment_records=64)
    appended = Node(tmp_path / "appended", segment_records=64)
    try:
        imu = ingested.approve("sensor_msgs/msg/Imu")
        assert appended.approve("sensor_msgs/msg/Imu") == imu
        ingested.bindings.bind(template_id=imu, msgtype="sensor_msgs/msg/Imu")
        for number, count in enumerate((125, 500)):
            folder = tmp_path / f"bag-{number}"
            folder.mkdir()
            path = write_bag(folder / "b.bag", "ros1", count, start_ns=START_NS + number)
            source = f"upload:v{number}"
            job = ingested.jobs.wait(ingested.jobs.submit(path, source, author).id, 60)
            assert job.status == "succeeded", job.error
        size = ingested.logs.size(imu)
        assert size == 500
        canonicals = [entry.record for entry in ingested.logs.entries(imu, 0, size)]
        for start in range(0, size, 50):
            records = [json.loads(record) for record in canonicals[start : start + 50]]
            appended.store.append(records, author=author)
        assert [e.record for e in appended.logs.entries(imu, 0, size)] == canonicals
        ingested.store.index_keywords()
        appended.store.index_keywords()
        for name in ("ingested", "appended"):
            views = tmp_path / name / "views" / imu
            assert len(list(views.glob("seg-*.json"))) == 7
        files = sorted(p.name for p in (tmp_path / "ingested" / "views" / imu).iterdir())
        assert files == sorted(p.name for p in (tmp_path / "appended" / "views" / imu).iterdir())
        for name in files:
            assert (tmp_path / "ingested" / "views" / imu / name).read_bytes() == (
                tmp_path / "appended" / "views" / imu / name
            ).read_bytes(), name
        mine, theirs = ingested.store.views(imu), appended.store.views(imu)
        assert mine is not None
        assert theirs is not None
        assert mine.snapshot() == theirs.snapshot()
        assert ingested.store.keywords.search(["imu_link"], imu) == {imu: set(range(size))}
        assert appended.store.keywords.search(["imu_link"], imu) == {imu: set(range(size))}
    finally:
        ingested.close()
        appended.close()


class RefusingBlobs:
    """A cas that fails, or that names bytes by a CID other than theirs."""

    def __init__(self, answer: str | None) -> None:
        self.answer = answer

    def put_many(self, blobs: Sequence[bytes]) -> list[str]:
        if self.answer is None:
            raise ConnectionError("cas is down")
        return [self.answer] * len(blobs)


class CountingBlobs(MemoryBlobs):
    """An in-memory cas that notes how many blobs each exchange with it held."""

    def __init__(self) -> None:
        super().__init__()
        self.exchanges: list[int] = []

    def put_many(self, blobs: Sequence[bytes]) -> list[str]:
        self.exchanges.append(len(blobs))
        return super().put_many(blobs)


def test_a_laser_scans_arrays_go_to_cas_a_batch_at_a_time(node: Node, tmp_path: Path) -> None:
    """cartographer's tiny recording (shared/data): each ``MultiEchoLaserScan`` holds arrays
    past the inline bound, and each array went to cas in a signed ``add`` of its own (5 ms).
    They go a batch at a time, and every record's array is among them."""
    node.blobs = CountingBlobs()
    node.store.arrays = ArrayOffload(node.store.arrays.inline_bytes, node.blobs.put_many)
    recording = SHARED_DATA / "rosbag1" / "cartographer_b0-2014-07-21-12-42-53-tiny.bag"
    scan = "sensor_msgs/msg/MultiEchoLaserScan"
    with Bag.open(recording) as opened:
        [typestore] = {c.typestore for c in opened.connections if c.msgtype == scan}
        scans = sum(c.count for c in opened.connections if c.msgtype == scan)
    version_id = node.approved(draft_template(typestore, scan))
    node.bindings.bind(template_id=version_id, msgtype=scan)
    copy = Path(shutil.copy(recording, tmp_path / "scans.bag"))
    job = node.jobs.wait(node.jobs.submit(copy, "upload:scans", authorship()).id, 120)
    assert (job.status, job.records_committed) == ("succeeded", scans), job.error
    stored = sum(node.blobs.exchanges)
    assert stored == len(node.blobs.files) > scans
    size = sum(len(data) for data in node.blobs.files.values())
    most = math.ceil(stored / BLOB_BATCH_COUNT) + math.ceil(size / BLOB_BATCH_BYTES)
    assert 1 < len(node.blobs.exchanges) <= most, node.blobs.exchanges
    assert max(node.blobs.exchanges) <= BLOB_BATCH_COUNT
    for index in range(scans):
        data = node.store.get(record_id(version_id, index)).record["data"]
        assert {data["ranges"], data["intensities"]} <= node.blobs.files.keys(), index
    assert json.loads(node.blobs.files[data["ranges"]])[0]["echoes"]


@pytest.mark.parametrize(
    ("answer", "message"),
    [(None, "cas is down"), ("bafkqaaa", "as bafkqaaa where their CID is bafkrei")],
    ids=["cas-down", "wrong-cid"],
)
def test_a_frame_cas_does_not_store_fails_the_job_before_anything_is_written(
    node: Node, tmp_path: Path, answer: str | None, message: str
) -> None:
    """Staging processes hand their frames to the job's blob sink: when cas fails or names
    them wrongly, the job fails with ``cas_unavailable`` and nothing is logged."""
    node.stage_in(3)
    imu = node.approve("sensor_msgs/msg/Imu")
    image = node.approve("sensor_msgs/msg/Image")
    node.bindings.bind(template_id=imu, msgtype="sensor_msgs/msg/Imu")
    node.bindings.bind(template_id=image, msgtype="sensor_msgs/msg/Image")
    node.blobs = RefusingBlobs(answer)  # type: ignore[assignment]
    job = node.jobs.wait(node.jobs.submit(bag(tmp_path, "c", 200), "upload:c", authorship()).id, 60)
    assert job.status == "failed"
    assert job.error is not None
    assert job.error["code"] == "cas_unavailable"
    assert message in job.error["message"]
    assert node.logs.template_ids() == []
    assert not (node.root / "jobs" / job.id / "staged").exists()


@WORKERS
@pytest.mark.parametrize("damage", ["truncate", "undefined"])
def test_a_failing_bag_appends_nothing(
    node: Node, tmp_path: Path, damage: str, workers: int
) -> None:
    node.stage_in(workers)
    imu = node.approve("sensor_msgs/msg/Imu")
    node.bindings.bind(template_id=imu, msgtype="sensor_msgs/msg/Imu")
    path = bag(tmp_path, "broken.bag", 3000, kind="ros1")
    if damage == "truncate":
        data = path.read_bytes()
        path.write_bytes(data[: len(data) * 2 // 3])
        expected = "bag_corrupt"
    else:
        path = tmp_path / "broken"
        shutil.copytree(
            Path(__file__).resolve().parents[5]
            / "shared/data/rosbag2/rosbag2_topics_and_service_events_sqlite3",
            path,
        )
        node.bindings.bind(template_id=imu, msgtype="test_msgs/srv/BasicTypes_Event")
        expected = "message_type_undefined"
    job = node.jobs.wait(node.jobs.submit(path, "upload:y", authorship()).id, 60)
    assert job.status == "failed"
    assert job.error is not None
    assert job.error["code"] == expected
    assert job.error["resumable"] is False
    if damage == "truncate":
        assert job.error["details"]["file"] is None
        assert job.error["message"].startswith("the bag")
    else:
        assert job.error["details"]["topic"].startswith("/test_service")
    assert node.logs.size(imu) == 0
    assert node.logs.template_ids() == []
    # The bag goes just after the failure is saved, which ``wait`` sees.
    wait_for(lambda: kept_files(node, job.id) == ["job.json"], "the failed job's bag removed", 10)


def kept_files(node: Node, job_id: str) -> list[str]:
    return sorted(path.name for path in (node.root / "jobs" / job_id).iterdir())


def test_a_failed_job_that_kept_its_bag_drops_it_at_open(node: Node, tmp_path: Path) -> None:
    """As jobs failed before bags were dropped at once, or one cut short between saving its
    failure and dropping its bag, left them."""
    path = bag(tmp_path, "broken.bag", 100, kind="ros1")
    path.write_bytes(path.read_bytes()[:-200])
    failed = node.jobs.wait(node.jobs.submit(path, "upload:f", authorship()).id, 60)
    assert failed.status == "failed"
    node.jobs.close()
    shutil.copy(
        bag(tmp_path, "old.bag", 10, kind="ros1"), node.root / "jobs" / failed.id / "bag.bag"
    )
    (node.root / "jobs" / failed.id / "staged").mkdir()
    node.jobs = node.open_jobs()
    assert kept_files(node, failed.id) == ["job.json"]
    assert node.jobs.get(failed.id).error == failed.error


@WORKERS
def test_a_damaged_mcap_chunk_fails_the_job_as_bag_corrupt(
    node: Node, tmp_path: Path, workers: int
) -> None:
    """Staging processes read the bag while the job checks its MCAP files; the damage the
    check finds is the job's error (whatever a worker made of the damaged bytes), with the
    file and offset, and nothing is logged."""
    node.stage_in(workers)
    source = Path(__file__).resolve().parents[5] / "shared/data/mcap/rosbag2_wbag_mcap"
    copy = tmp_path / "wbag"
    shutil.copytree(source, copy)
    with Bag.open(copy) as intact:
        bound = {c.msgtype: c.typestore for c in intact.connections if c.typestore and c.count}
    for msgtype, store in bound.items():
        version_id = node.approved(draft_template(store, msgtype))
        node.bindings.bind(template_id=version_id, msgtype=msgtype)
    storage = copy / "wbag_2.mcap"
    damaged = bytearray(storage.read_bytes())
    damaged[4000:4016] = bytes(16)
    storage.write_bytes(bytes(damaged))
    job = node.jobs.wait(node.jobs.submit(copy, "upload:w", authorship()).id, 60)
    assert job.status == "failed"
    assert job.error is not None
    assert job.error["code"] == "bag_corrupt"
    assert job.error["details"] == {"file": "wbag_2.mcap", "offset": 45}
    assert job.error["message"].startswith("wbag_2.mcap at byte 45: ")
    assert bound
    assert all(node.logs.size(report.template) == 0 for report in job.topics if report.template)
    assert node.logs.template_ids() == []


@WORKERS
def test_a_value_the_template_refuses_fails_before_anything_is_written(
    node: Node, tmp_path: Path, workers: int
) -> None:
    """The refused value is the last message: with three windows, the last process finds it
    and the job fails with nothing written by any of them."""
    node.stage_in(workers)
    imu = node.approve("sensor_msgs/msg/Imu")
    node.bindings.bind(template_id=imu, msgtype="sensor_msgs/msg/Imu")
    path = write_bag(tmp_path / "far", "sqlite3", 30, start_ns=START_NS)
    far = tmp_path / "far2"
    store = typestore_for("sqlite3")
    from rosbags.rosbag2 import Writer

    from tests.bagfactory import imu as make_imu

    with Writer(far, version=9) as writer:
        connection = writer.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=store)
        for step in range(30):
            t_ns = START_NS + step * 10_000_000
            message = make_imu(store, step, t_ns)
            if step == 29:
                message.angular_velocity.x = float("nan")
            writer.write(connection, t_ns, store.serialize_cdr(message, "sensor_msgs/msg/Imu"))
    assert path.exists()
    job = node.jobs.wait(node.jobs.submit(far, "upload:z", authorship()).id, 60)
    assert job.status == "failed"
    assert job.error is not None
    assert job.error["code"] == "record_invalid"
    assert job.error["details"]["field"] == "angular_velocity.x"
    assert node.logs.size(imu) == 0


@WORKERS
def test_a_large_array_cas_cannot_take_fails_the_job_before_anything_is_written(
    node: Node, tmp_path: Path, workers: int
) -> None:
    """Covariances above the inline bound go to cas while staging; a node without a cas
    fails the job with ``cas_unavailable`` naming the field, and logs nothing."""
    imu = node.approve("sensor_msgs/msg/Imu")
    node.bindings.bind(template_id=imu, msgtype="sensor_msgs/msg/Imu")
    node.jobs.close()
    node.store.close()
    node.store = RecordStore(node.root, node.logs, node.catalog, array_inline_bytes=16)
    node.jobs = node.open_jobs(staging_workers=workers)
    job = node.jobs.wait(node.jobs.submit(bag(tmp_path, "o", 20), "upload:o", authorship()).id, 60)
    assert job.status == "failed"
    assert job.error is not None
    assert job.error["code"] == "cas_unavailable"
    assert job.error["details"]["field"].endswith("_covariance")
    assert "no cas" in job.error["message"]
    assert node.logs.size(imu) == 0


def test_an_interrupted_commit_is_settled_exactly_once(node: Node, tmp_path: Path) -> None:
    """A crash between a batch's append and its acknowledgement in the job: on reopen the batch
    is found in the log by its authorship and not appended again."""
    imu = node.approve("sensor_msgs/msg/Imu")
    node.bindings.bind(template_id=imu, msgtype="sensor_msgs/msg/Imu")
    author = authorship("nonce-crash-000000")
    job = node.jobs.wait(node.jobs.submit(bag(tmp_path, "c", 100), "upload:c", author).id, 60)
    assert job.status == "succeeded"
    assert node.logs.size(imu) == 80
    job_file = node.root / "jobs" / job.id / "job.json"
    node.jobs.close()
    state = json.loads(job_file.read_text())
    # the state as it was on disk just after appending the second batch of 50 (30 records)
    state.update(
        status="committing",
        committed={imu: 50},
        records_committed=50,
        intent={"template": imu, "start": 50, "count": 30, "log_size": 50},
    )
    staged = node.root / "jobs" / job.id / "staged"
    staged.mkdir()
    canonicals = [entry.record for entry in node.logs.entries(imu, 0, 80)]

    def spool() -> None:
        writer = SpoolWriter(staged, node.catalog.approved(imu), 0)
        for canonical in canonicals:
            writer.write(canonical)
        writer.close()

    spool()
    job_file.write_text(json.dumps(state))
    node.jobs = node.open_jobs()
    resumed = node.jobs.wait(job.id, 60)
    assert resumed.status == "succeeded"
    assert resumed.records_committed == 80
    assert node.logs.size(imu) == 80
    assert resumed.record_ids[imu][-1] == "imu-1-79"
    # and when the crash came before the append, the batch is appended on reopen
    node.jobs.close()
    state.update(intent={"template": imu, "start": 50, "count": 30, "log_size": 80})
    job_file.write_text(json.dumps(state))
    staged.mkdir(exist_ok=True)
    spool()
    node.jobs = node.open_jobs()
    again = node.jobs.wait(job.id, 60)
    assert again.status == "succeeded"
    assert node.logs.size(imu) == 110


def test_unknown_job(node: Node) -> None:
    with pytest.raises(JobNotFound):
        node.jobs.get("0" * 24)


def test_job_state_round_trips() -> None:
    job = Job(id="a", bag="cid:b", author=asdict(authorship()))
    assert Job.from_json(json.loads(json.dumps(asdict(job)))) == job


def _traced_peak(node: Node, path: Path) -> int:
    """Bytes the ingest of ``path`` held at most in this process (the service's: receiving
    frames from its staging process, committing) beyond what was held before it started."""
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        job = node.jobs.wait(node.jobs.submit(path, "upload:m", authorship()).id, 300)
        node.store.index_keywords()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert job.status == "succeeded", job.error
    return peak - before


def _staging_peak(node: Node, path: Path, spool: Path) -> int:
    """Bytes staging ``path`` whole held at most beyond what was held before, staged here as
    its staging process does."""
    spool.mkdir()
    with Bag.open(path) as opened:
        plans = {}
        for connection in opened.connections:
            template_id = node.bindings.resolve(connection.topic, connection.msgtype)
            assert template_id is not None
            template = node.catalog.approved(template_id)
            plans[connection.topic, connection.msgtype] = compile_plan(connection, template)
        tracemalloc.start()
        try:
            before = tracemalloc.get_traced_memory()[0]
            staged = stage_window(
                opened,
                plans,
                (None, None),
                spool,
                0,
                node.author,
                node.store.arrays,
                node.blobs,
                lambda _: None,
            )
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
    assert sum(staged.records.values()) == sum(c.count for c in opened.connections)
    return peak - before


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_memory_does_not_follow_the_size_of_the_bag(
    node: Node, tmp_path: Path, kind: BagKind
) -> None:
    """A bag of 40 camera frames (0.9 MB each) and one of 10 are staged, and ingested, with
    the same peak give or take 4 frames: frames, records and spools are streamed, never
    gathered (a list of records or of image bytes would hold 30 frames' worth more), in the
    staging process and in the service."""
    for msgtype in TOPICS.values():
        node.bindings.bind(template_id=node.approve(msgtype), msgtype=msgtype)
    node.blobs = CasBlobs(lambda blobs: [str(import_bytes(data)[1]) for data in blobs])  # type: ignore[assignment]
    store = typestore_for(kind)
    bags = {}
    for name, frames in (("warm", 10), ("small", 10), ("large", 40)):
        path = tmp_path / (f"{name}.bag" if kind == "ros1" else name)
        bags[name] = write_messages(path, kind, store, camera_run(store, frames))
    _staging_peak(node, bags["warm"], tmp_path / "spool-warm")
    small = _staging_peak(node, bags["small"], tmp_path / "spool-small")
    large = _staging_peak(node, bags["large"], tmp_path / "spool-large")
    assert large - small < 4 * FRAME_BYTES, ("staging", small, large)
    _traced_peak(node, bags["warm"])
    small, large = _traced_peak(node, bags["small"]), _traced_peak(node, bags["large"])
    assert large - small < 4 * FRAME_BYTES, ("ingest", small, large)


def test_the_blob_memo_forgets_the_oldest_content() -> None:
    """Identical frames are stored once, and the memo of what was stored stays bounded."""
    added: list[list[bytes]] = []

    def add(blobs: Sequence[bytes]) -> list[str]:
        added.append(list(blobs))
        return [str(import_bytes(data)[1]) for data in blobs]

    blobs = CasBlobs(add, remembered=2)
    for data in (b"a", b"a", b"b", b"c", b"c", b"a"):
        blobs.put(data)
    assert added == [[b"a"], [b"b"], [b"c"], [b"a"]]
    cids = blobs.put_many([b"d", b"a", b"d", b"e"])
    assert added[4:] == [[b"d", b"e"]]
    assert cids == [str(import_bytes(data)[1]) for data in (b"d", b"a", b"d", b"e")]


def test_a_staging_process_silent_past_the_stall_bound_fails_its_job(
    node: Node, tmp_path: Path
) -> None:
    """A message that stages for longer than the bound (8 MiB of ROS 1 ``std_msgs/Bool[]``,
    memory unbounded: about 12 s) fails its job as stalled, the process stopped, instead of
    holding the one ingest thread for as long as it runs; nothing is stored, the next bag
    ingests."""
    node.jobs.close()
    node.jobs = IngestJobs(
        node.root / "jobs",
        node.store,
        node.logs,
        node.bindings,
        lambda: node.blobs.put_many,
        stall_s=5.0,
    )
    seq = node.approved({"name": "flag_seq", "version": 1, "fields": {"seq": "int"}})
    node.bindings.bind(template_id=seq, topic="/flags")
    slow = write_flags_bag(tmp_path / "slow.bag", 8 * 1024**2)
    failed = node.jobs.wait(node.jobs.submit(slow, "upload:s", authorship()).id, 60)
    assert failed.status == "failed"
    assert failed.error == {
        "code": "ingest_stalled",
        "message": "staging process 0 sent nothing for 5 s: a message it stages takes "
        "longer than any should (ROBOCLOUD_STORAGE_INGEST_STALL_S)",
        "details": {"part": 0},
        "resumable": False,
    }
    assert node.logs.size(seq) == 0
    quick = write_flags_bag(tmp_path / "quick.bag", 16)
    done = node.jobs.wait(node.jobs.submit(quick, "upload:q", authorship()).id, 60)
    assert done.status == "succeeded", done.error
    assert [json.loads(e.record)["data"] for e in node.logs.entries(seq, 0, 1)] == [{"seq": 7}]


def test_a_failure_the_disk_cannot_save_leaves_the_ingest_worker_running(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A job failed on a full disk and saving its failure failed too: the exception killed
    the only ingest thread, and every job accepted after it stayed queued."""
    node = Node(tmp_path / "node")
    imu = node.approve("sensor_msgs/msg/Imu")
    node.bindings.bind(template_id=imu, msgtype="sensor_msgs/msg/Imu")

    def no_space(*args: object, **kwargs: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    def full_disk(*args: object) -> None:
        monkeypatch.setattr(ingest, "atomic_write", no_space)
        no_space()

    monkeypatch.setattr(node.jobs, "_plan", full_disk)
    first = node.jobs.submit(
        bag(tmp_path, "b1", 20), "upload:1", authorship("nonce-1111111111111111")
    )
    assert node.jobs.wait(first.id, 60).status == "failed"
    monkeypatch.undo()
    second = node.jobs.submit(
        bag(tmp_path, "b2", 20), "upload:2", authorship("nonce-2222222222222222")
    )
    finished = node.jobs.wait(second.id, 120)
    assert finished.status == "succeeded"
    assert finished.records_committed > 0


def test_a_job_failed_while_committing_resumes_with_each_record_once(
    node: Node, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The disk fills after the first batch of 50: the job fails resumable, its spool kept;
    resumed, it appends the other 110 and none twice. A job that succeeded, or failed before
    committing anything, does not resume."""
    imu = node.approve("sensor_msgs/msg/Imu")
    node.bindings.bind(template_id=imu, msgtype="sensor_msgs/msg/Imu")
    fail_after_first_batch(monkeypatch)
    submitted = node.jobs.submit(bag(tmp_path, "b", 200), "upload:b", authorship())
    failed = node.jobs.wait(submitted.id, 60)
    assert failed.status == "failed"
    assert failed.error is not None
    assert (failed.error["resumable"], failed.records_committed) == (True, 50)
    assert "No space left on device" in failed.error["message"]
    assert node.logs.size(imu) == 50

    monkeypatch.undo()
    node.jobs.max_pending = 0
    with pytest.raises(TooManyJobs, match="0 ingest jobs are queued or running"):
        node.jobs.resume(failed.id)
    assert node.jobs.get(failed.id).status == "failed", "a resume refused changes nothing"
    node.jobs.max_pending = 16
    assert node.jobs.resume(failed.id).status == "committing"
    done = node.jobs.wait(failed.id, 60)
    assert done.status == "succeeded", done.error
    assert done.records_committed == node.logs.size(imu) == 160
    assert len({entry.record for entry in node.logs.entries(imu, 0, 160)}) == 160
    with pytest.raises(ingest.JobNotResumable, match="is succeeded"):
        node.jobs.resume(failed.id)


def fail_after_first_batch(monkeypatch: pytest.MonkeyPatch) -> None:
    """The disk fills once the first batch is appended: the job fails while committing."""
    append = RecordStore.append_prepared
    appended: list[int] = []

    def filling(self: RecordStore, *args: Any, **kwargs: Any) -> int:
        if appended:
            raise OSError(errno.ENOSPC, "No space left on device")
        appended.append(append(self, *args, **kwargs))
        return appended[-1]

    monkeypatch.setattr(RecordStore, "append_prepared", filling)


def until_expired(node: Node, job_id: str, timeout_s: float = 10.0) -> ingest.Job:
    """The job once the worker saved it as not resumable and then dropped its inputs."""
    deadline = time.monotonic() + timeout_s
    while (job := node.jobs.get(job_id)).error is None or job.error["resumable"]:
        assert time.monotonic() < deadline, "the job stayed resumable"
        time.sleep(0.05)
    while kept_files(node, job_id) != ["job.json"]:
        assert time.monotonic() < deadline, f"the job kept {kept_files(node, job_id)}"
        time.sleep(0.05)
    return job


def test_a_job_nobody_resumes_in_time_drops_its_bag_and_spool(
    node: Node, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A job failed while committing kept its bag (16 GiB at most) and spool for a resume
    that may never come, until a thousand later jobs had finished."""
    imu = node.approve("sensor_msgs/msg/Imu")
    node.bindings.bind(template_id=imu, msgtype="sensor_msgs/msg/Imu")
    node.jobs.close()
    node.jobs = node.open_jobs(keep_resumable_s=0.5)
    fail_after_first_batch(monkeypatch)
    before = time.time_ns()
    failed = node.jobs.wait(
        node.jobs.submit(bag(tmp_path, "b", 200), "upload:b", authorship()).id, 60
    )
    assert failed.error is not None
    assert failed.error["resumable"]
    assert before + 5e8 <= failed.error["resumable_until_ns"] <= time.time_ns() + 5e8
    assert kept_files(node, failed.id) == ["bag", "job.json", "staged"]
    expired = until_expired(node, failed.id)
    assert expired.status == "failed"
    assert expired.error is not None
    assert expired.error["message"].endswith(
        "; not resumed within 0.5 s, its bag was removed: the bag sent again finishes the job"
    )
    assert "No space left on device" in expired.error["message"]
    assert (expired.records_committed, node.logs.size(imu)) == (50, 50), "committed records stay"
    with pytest.raises(ingest.JobNotResumable):
        node.jobs.resume(failed.id)


def test_a_resumable_job_saved_before_its_time_was_recorded_expires_after_a_restart(
    node: Node, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A job.json written before ``resumable_until_ns`` existed counts from its last save."""
    imu = node.approve("sensor_msgs/msg/Imu")
    node.bindings.bind(template_id=imu, msgtype="sensor_msgs/msg/Imu")
    fail_after_first_batch(monkeypatch)
    failed = node.jobs.wait(
        node.jobs.submit(bag(tmp_path, "b", 200), "upload:b", authorship()).id, 60
    )
    assert failed.error is not None
    assert failed.error["resumable"]
    node.jobs.close()
    saved = node.root / "jobs" / failed.id / "job.json"
    document = json.loads(saved.read_text())
    del document["error"]["resumable_until_ns"]
    document["updated_ns"] = time.time_ns()
    saved.write_text(json.dumps(document))
    node.jobs = node.open_jobs(keep_resumable_s=0.5)
    expired = until_expired(node, failed.id)
    assert expired.updated_ns >= document["updated_ns"] + 5e8, "expired before its time"
    assert expired.error is not None
    assert "not resumed within 0.5 s" in expired.error["message"]
