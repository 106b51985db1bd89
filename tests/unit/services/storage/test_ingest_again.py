"""A bag sent again: by the same robot, no topic is ingested twice; while its job runs, the
resend gets that job; while its job awaits a resume, the resend is refused."""

from __future__ import annotations

import hashlib
import shutil
import sqlite3
from collections.abc import Iterator
from contextlib import closing
from pathlib import Path

import pytest

from services.storage.ingest import BagAwaitsResume, IngestJobs
from services.storage.ingested import IngestedBags
from services.storage.recordstore import Authorship
from tests.unit.services.storage.test_ingest import (
    Node,
    authorship,
    bag,
    fail_after_first_batch,
    until_expired,
)


@pytest.fixture
def node(tmp_path: Path) -> Iterator[Node]:
    created = Node(tmp_path / "node")
    yield created
    created.close()


def imu_bound(node: Node) -> str:
    """An approved IMU template, bound to the IMU message type: its id."""
    imu = node.approve("sensor_msgs/msg/Imu")
    node.bindings.bind(template_id=imu, msgtype="sensor_msgs/msg/Imu")
    return imu


def job_dirs(node: Node) -> list[str]:
    return sorted(path.parent.name for path in (node.root / "jobs").glob("*/job.json"))


def test_the_same_robot_s_bag_sent_again_adds_no_record_and_publishes_nothing(
    node: Node, tmp_path: Path
) -> None:
    """The second job of one robot's bag skips every topic the first ingested, naming it:
    the logs keep 160 IMU records, not 320. A topic bound since is new data, ingested."""
    imu = imu_bound(node)
    robot = authorship("nonce-1111111111111111")
    first = node.jobs.wait(node.jobs.submit(bag(tmp_path, "b1", 200), "upload:b", robot).id, 60)
    assert (first.status, first.records_committed, node.logs.size(imu)) == ("succeeded", 160, 160)

    again = node.jobs.wait(node.jobs.submit(bag(tmp_path, "b2", 200), "upload:b", robot).id, 60)
    assert again.id != first.id
    assert (again.status, again.records_committed, again.records_staged) == ("succeeded", 0, 0)
    assert again.messages_total == 0
    reports = {report.topic: report for report in again.topics}
    assert reports["/imu"].template == imu
    assert reports["/imu"].ingested_by == first.id
    assert reports["/imu"].skipped == f"ingested from this bag into {imu} by job {first.id}"
    assert again.to_json()["unbound_topics"] == ["/gps", "/camera/image_raw"]
    assert again.record_ids == {}
    assert node.logs.size(imu) == 160

    gps = node.approve("sensor_msgs/msg/NavSatFix")
    node.bindings.bind(template_id=gps, topic="/gps")
    third = node.jobs.wait(node.jobs.submit(bag(tmp_path, "b3", 200), "upload:b", robot).id, 60)
    assert (third.status, third.records_committed) == ("succeeded", 20), third.error
    assert {report.topic: report.ingested_by for report in third.topics} == {
        "/imu": first.id,
        "/gps": None,
        "/camera/image_raw": None,
    }
    assert (node.logs.size(imu), node.logs.size(gps)) == (160, 20)


def test_what_a_bag_gave_is_remembered_after_a_restart_and_its_jobs_forgotten(
    node: Node, tmp_path: Path
) -> None:
    """The node keeps its last ``keep_finished`` jobs; what they ingested outlives them."""
    imu = imu_bound(node)
    robot = authorship()
    node.jobs.close()
    node.jobs = node.open_jobs(keep_finished=0)
    first = node.jobs.wait(node.jobs.submit(bag(tmp_path, "b1", 50), "upload:b", robot).id, 60)
    other = node.jobs.submit(bag(tmp_path, "o", 50), "upload:other", authorship())
    assert node.jobs.wait(other.id, 60).status == "succeeded"
    assert job_dirs(node) == [other.id], "the first job is forgotten"
    node.jobs.close()
    node.jobs = node.open_jobs()
    again = node.jobs.wait(node.jobs.submit(bag(tmp_path, "b2", 50), "upload:b", robot).id, 60)
    assert again.records_committed == 0
    assert [report.ingested_by for report in again.topics if report.template] == [first.id]
    assert node.logs.size(imu) == 2 * 40


def test_another_robot_s_copy_or_another_bag_is_ingested(node: Node, tmp_path: Path) -> None:
    """Records are each robot's own: a second robot's copy of the bag is its data; and the
    same robot's different bag (another digest) is another bag."""
    imu = imu_bound(node)
    robot = authorship()
    jobs = [
        node.jobs.submit(bag(tmp_path, "b1", 50), "upload:b", robot),
        node.jobs.submit(bag(tmp_path, "b2", 50), "upload:b", authorship()),
        node.jobs.submit(bag(tmp_path, "b3", 50), "upload:c", robot),
    ]
    finished = [node.jobs.wait(job.id, 60) for job in jobs]
    assert [job.records_committed for job in finished] == [40, 40, 40]
    assert node.logs.size(imu) == 120


def copies(path: Path, count: int) -> list[Path]:
    """``count`` copies of the file ``path`` (a job takes the file it is given)."""
    made = []
    for index in range(count):
        copy = path.with_name(f"{path.name}-copy{index}")
        shutil.copyfile(path, copy)
        made.append(copy)
    return made


def test_one_file_sent_uploaded_and_by_two_cids_is_one_bag(node: Node, tmp_path: Path) -> None:
    """A bag file is the same bag however it comes: uploaded, by its CID, by the CID of
    another import of it. Each way was a bag of its own, and the same IMU messages were
    stored three times (120 records for 40)."""
    imu = imu_bound(node)
    robot = authorship()
    original = bag(tmp_path, "run.bag", 50, kind="ros1")
    digest = hashlib.sha256(original.read_bytes()).hexdigest()
    first_copy, second_copy, third_copy = copies(original, 3)
    first = node.jobs.wait(node.jobs.submit(first_copy, f"upload:{digest}", robot).id, 60)
    assert first.records_committed == 40
    for cid, copy in [("bafybeiaone", second_copy), ("bafkreitwo", third_copy)]:
        again = node.jobs.wait(node.jobs.submit(copy, f"cid:{cid}", robot).id, 60)
        assert (again.status, again.records_committed) == ("succeeded", 0), again.error
        (imu_report,) = [report for report in again.topics if report.template]
        assert imu_report.ingested_by == first.id
        assert again.content == f"sha256:{digest}"
    assert node.logs.size(imu) == 40


def test_a_different_file_by_cid_is_another_bag(node: Node, tmp_path: Path) -> None:
    imu = imu_bound(node)
    robot = authorship()
    node.jobs.wait(
        node.jobs.submit(bag(tmp_path, "a.bag", 50, "ros1"), "cid:bafkreia", robot).id, 60
    )
    other = bag(tmp_path, "b.bag", 60, "ros1")
    done = node.jobs.wait(node.jobs.submit(other, "cid:bafkreib", robot).id, 60)
    assert done.records_committed == 48
    assert node.logs.size(imu) == 88


def test_an_older_node_s_uploads_are_named_by_their_content_once(tmp_path: Path) -> None:
    """Its table named uploads ``upload:<hex>``: they are ``sha256:<hex>`` after the next
    start, so a CID of the same file finds them; a CID bag's row is left as it was."""
    path = tmp_path / "ingested.sqlite"
    IngestedBags(path).close()
    with closing(sqlite3.connect(path)) as older, older:
        older.execute("PRAGMA user_version = 0")
        older.executemany(
            "INSERT INTO ingested VALUES (?, ?, ?, ?, ?, ?)",
            [
                ("0xab", "upload:00ff", "/imu", "sensor_msgs/msg/Imu", "imu@1", "job1"),
                ("0xab", "cid:bafkreia", "/gps", "sensor_msgs/msg/NavSatFix", "gps@1", "job2"),
            ],
        )
    for _ in range(2):
        table = IngestedBags(path)
        assert table.ingested("0xAB", "sha256:00ff") == {
            ("/imu", "sensor_msgs/msg/Imu", "imu@1"): "job1"
        }
        assert table.ingested("0xab", "upload:00ff") == {}
        assert table.ingested("0xab", "cid:bafkreia") == {
            ("/gps", "sensor_msgs/msg/NavSatFix", "gps@1"): "job2"
        }
        table.close()


def test_a_bag_sent_again_while_its_job_runs_gets_that_job(node: Node, tmp_path: Path) -> None:
    """A robot whose answer was lost sends the bag again: it gets the job the first request
    made, whose bag stays the only one kept; the resent file is not taken."""
    imu = imu_bound(node)
    robot = authorship()
    ahead = node.jobs.submit(bag(tmp_path, "ahead", 4000), "upload:ahead", authorship())
    queued = node.jobs.submit(bag(tmp_path, "b1", 50), "upload:b", robot)
    resent = bag(tmp_path, "b2", 50)
    answered = node.jobs.submit(resent, "upload:b", robot)
    assert answered.id == queued.id
    assert answered.status in ("queued", "staging", "committing")
    assert resent.exists(), "the resent bag is the caller's to remove"
    assert job_dirs(node) == sorted([ahead.id, queued.id])
    assert node.jobs.wait(queued.id, 120).records_committed == 40
    assert node.logs.size(imu) == 3200 + 40


def test_a_bag_whose_job_awaits_a_resume_is_refused_again(
    node: Node, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Part of its records are in: a second job would store them twice; the resume commits
    the rest once. Refused before it is a job: nothing is taken, stored or queued."""
    imu = imu_bound(node)
    fail_after_first_batch(monkeypatch)
    robot = authorship()
    failed = node.jobs.wait(node.jobs.submit(bag(tmp_path, "b1", 200), "upload:b", robot).id, 60)
    assert failed.error is not None
    assert failed.error["resumable"]
    monkeypatch.undo()
    resent = bag(tmp_path, "b2", 200)
    with pytest.raises(BagAwaitsResume, match=f"ingest job {failed.id} of this bag"):
        node.jobs.submit(resent, "upload:b", robot)
    assert resent.exists()
    assert job_dirs(node) == [failed.id]
    assert node.logs.size(imu) == 50
    assert node.jobs.wait(node.jobs.resume(failed.id).id, 60).records_committed == 160
    assert node.logs.size(imu) == 160


def expired_after_first_batch(
    node: Node, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, robot: Authorship
) -> str:
    """A job of ``robot``'s bag ``upload:b`` that committed 50 of its 160 IMU records, then
    failed and was not resumed in time: its id."""
    node.jobs.close()
    node.jobs = node.open_jobs(keep_resumable_s=0.2, keep_finished=0)
    fail_after_first_batch(monkeypatch)
    failed = node.jobs.submit(bag(tmp_path, "b1", 200), "upload:b", robot)
    expired = until_expired(node, node.jobs.wait(failed.id, 60).id)
    monkeypatch.undo()
    assert expired.error is not None
    assert expired.error["message"].endswith("the bag sent again finishes the job")
    return expired.id


def test_a_bag_sent_again_after_its_job_expired_finishes_that_job(
    node: Node, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A job failed while committing and not resumed in time kept its 50 records and lost
    its bag: the robot's resend was a new job that appended all 160 again, and the anchored
    logs held 210. The resend now goes to that job, which commits past its 50 records. The
    job is kept meanwhile (``keep_finished=0``), or the node forgot that it ever ran."""
    imu = imu_bound(node)
    robot = authorship()
    expired = expired_after_first_batch(node, tmp_path, monkeypatch, robot)
    other = node.jobs.submit(bag(tmp_path, "o", 50), "upload:other", authorship())
    assert node.jobs.wait(other.id, 60).status == "succeeded"
    assert job_dirs(node) == sorted([expired, other.id])

    resent = bag(tmp_path, "b2", 200)
    answered = node.jobs.submit(resent, "upload:b", robot)
    assert (answered.id, answered.status, answered.error) == (expired, "committing", None)
    assert not resent.exists(), "the job took the bag"
    finished = node.jobs.wait(expired, 60)
    assert (finished.status, finished.records_committed) == ("succeeded", 160), finished.error
    assert finished.record_ids == {imu: ["imu-1-0", "imu-1-199"]}
    assert node.logs.size(imu) == 40 + 160
    assert [path.name for path in (node.root / "jobs" / expired).iterdir()] == ["job.json"]

    again = node.jobs.wait(node.jobs.submit(bag(tmp_path, "b3", 200), "upload:b", robot).id, 60)
    assert [report.ingested_by for report in again.topics if report.template] == [expired]
    assert node.logs.size(imu) == 200


def test_a_bag_sent_again_after_its_job_expired_follows_that_job_s_plan(
    node: Node, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The bag is staged again by the topics the job began with: a topic bound since is
    the next job's. Staging it by the new bindings gave other records than those staged,
    and the job could only fail again."""
    imu = imu_bound(node)
    robot = authorship()
    expired = expired_after_first_batch(node, tmp_path, monkeypatch, robot)
    gps = node.approve("sensor_msgs/msg/NavSatFix")
    node.bindings.bind(template_id=gps, topic="/gps")

    finished = node.jobs.wait(node.jobs.submit(bag(tmp_path, "b2", 200), "upload:b", robot).id, 60)
    assert finished.id == expired
    assert (finished.status, finished.records_committed) == ("succeeded", 160), finished.error
    assert (node.logs.size(imu), node.logs.size(gps)) == (160, 0)

    again = node.jobs.wait(node.jobs.submit(bag(tmp_path, "b3", 200), "upload:b", robot).id, 60)
    assert again.records_committed == 20
    assert (node.logs.size(imu), node.logs.size(gps)) == (160, 20)


def test_a_node_that_ingested_before_the_table_fills_it_from_its_jobs(
    node: Node, tmp_path: Path
) -> None:
    """Upgrading a node: its succeeded jobs say what their bags gave."""
    imu = imu_bound(node)
    robot = authorship()
    first = node.jobs.wait(node.jobs.submit(bag(tmp_path, "b1", 50), "upload:b", robot).id, 60)
    node.jobs.close()
    (node.root / "jobs" / "ingested.sqlite").unlink()
    node.jobs = node.open_jobs()
    assert isinstance(node.jobs, IngestJobs)
    again = node.jobs.wait(node.jobs.submit(bag(tmp_path, "b2", 50), "upload:b", robot).id, 60)
    assert [report.ingested_by for report in again.topics if report.template] == [first.id]
    assert node.logs.size(imu) == 40
