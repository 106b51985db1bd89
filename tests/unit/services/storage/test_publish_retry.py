"""A dataset whose publishing fails (cas or the ledger out) is published again later, its bag
kept until then: before, one failure left it unpublished for good and removed the bag."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from services.storage.ingest import DatasetUnpublishable, Job, Publish
from tests.unit.services.storage.test_ingest import Node, authorship, bag
from tests.waiting import wait_for

PUBLISHED = {"cid": "bafy-bag", "description": "bafy-description", "tx": "0x01"}


class OutageThenUp:
    """A publisher out for its first ``failures`` calls, like a node whose cas is down; it
    notes whether the job's bag was there at each call."""

    def __init__(self, failures: int) -> None:
        self.failures = failures
        self.calls: list[tuple[int, bool]] = []

    def __call__(
        self, job: Job, bag: Path, save_advertise_tx: Callable[[dict[str, Any]], None]
    ) -> dict[str, Any]:
        self.calls.append((job.publish_attempts, bag.exists()))
        if len(self.calls) <= self.failures:
            raise ConnectionError(f"cas is out (call {len(self.calls)})")
        return PUBLISHED


@pytest.fixture
def open_node(tmp_path: Path) -> Iterator[Callable[..., Node]]:
    """A node whose jobs retry publishing as ``options`` say; closed at the end."""
    opened: list[Node] = []

    def start(publisher: Publish, **options: Any) -> Node:
        node = Node(tmp_path / "node", publish=publisher)
        node.jobs.close()
        node.jobs = node.open_jobs(**options)
        node.bindings.bind(
            template_id=node.approve("sensor_msgs/msg/Imu"), msgtype="sensor_msgs/msg/Imu"
        )
        opened.append(node)
        return node

    yield start
    for node in opened:
        node.close()


def job_files(node: Node, job_id: str) -> list[str]:
    return sorted(path.name for path in (node.root / "jobs" / job_id).iterdir())


def ingest(node: Node, tmp_path: Path) -> Job:
    submitted = node.jobs.submit(bag(tmp_path, "b", 200), "upload:b", authorship())
    return node.jobs.wait(submitted.id, 60)


def test_a_failed_publish_is_tried_again_with_the_bag_kept_until_it_is_published(
    open_node: Callable[..., Node], tmp_path: Path
) -> None:
    publisher = OutageThenUp(failures=2)
    node = open_node(publisher, publish_retry_s=1.0)
    job = ingest(node, tmp_path)
    assert job.status == "succeeded"
    assert job.records_committed == 160
    dataset = job.to_json()["dataset"]
    assert dataset["error"] == "cas is out (call 1)"
    assert dataset["attempts"] == 1
    assert dataset["next_attempt_ns"] > job.updated_ns - 1
    assert job_files(node, job.id) == ["bag", "job.json"]

    published = wait_for(
        lambda: node.jobs.get(job.id).dataset == PUBLISHED and node.jobs.get(job.id),
        "the third attempt",
        timeout_s=30,
    )
    assert published.to_json()["dataset"] == PUBLISHED
    assert published.publish_retry_ns is None
    assert publisher.calls == [(1, True), (2, True), (3, True)]
    wait_for(lambda: job_files(node, job.id) == ["job.json"], "the bag to be removed", 10)
    assert node.logs.size("imu@1") == 160, "no record appended again"


def test_publishing_gives_up_after_its_attempts_and_removes_the_bag(
    open_node: Callable[..., Node], tmp_path: Path
) -> None:
    publisher = OutageThenUp(failures=100)
    node = open_node(publisher, publish_retry_s=0.1, publish_attempts=3)
    job = ingest(node, tmp_path)
    wait_for(lambda: len(publisher.calls) == 3, "three attempts", timeout_s=30)
    wait_for(lambda: job_files(node, job.id) == ["job.json"], "the bag to be removed", 10)
    final = node.jobs.get(job.id)
    assert final.to_json()["dataset"] == {"error": "cas is out (call 3)", "attempts": 3}
    assert final.status == "succeeded"
    assert publisher.calls == [(1, True), (2, True), (3, True)]


class Refused:
    """A publisher whose description the node's own rules refuse, as one of 257 templates."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(
        self, job: Job, bag: Path, save_advertise_tx: Callable[[dict[str, Any]], None]
    ) -> dict[str, Any]:
        self.calls += 1
        raise DatasetUnpublishable("the description has 257 record counts, more than 256")


def test_a_description_the_node_refuses_is_not_tried_again(
    open_node: Callable[..., Node], tmp_path: Path
) -> None:
    """No attempt can change the refusal: the job gives up at once and drops its bag, where it
    kept it through eight attempts and ten minutes."""
    publisher = Refused()
    node = open_node(publisher, publish_retry_s=0.1)
    job = ingest(node, tmp_path)
    assert job.status == "succeeded"
    assert job.to_json()["dataset"] == {
        "error": "the description has 257 record counts, more than 256",
        "attempts": 1,
    }
    assert job.publish_retry_ns is None
    assert job_files(node, job.id) == ["job.json"]
    time.sleep(0.5)
    assert publisher.calls == 1


def test_a_retry_pending_when_the_node_stopped_is_made_after_the_next_start(
    open_node: Callable[..., Node], tmp_path: Path
) -> None:
    down = OutageThenUp(failures=100)
    node = open_node(down, publish_retry_s=1.0)
    job = ingest(node, tmp_path)
    node.jobs.close()
    attempts = node.jobs.get(job.id).publish_attempts

    up = OutageThenUp(failures=0)
    node.publish = up
    node.jobs = node.open_jobs()
    wait_for(lambda: node.jobs.get(job.id).dataset == PUBLISHED, "the retry", timeout_s=30)
    assert up.calls == [(attempts + 1, True)]
    wait_for(lambda: job_files(node, job.id) == ["job.json"], "the bag to be removed", 10)


def test_a_retry_pending_when_publishing_is_turned_off_removes_the_bag(
    open_node: Callable[..., Node], tmp_path: Path
) -> None:
    node = open_node(OutageThenUp(failures=100), publish_retry_s=1.0)
    job = ingest(node, tmp_path)
    node.jobs.close()

    node.publish = None
    node.jobs = node.open_jobs()
    wait_for(lambda: job_files(node, job.id) == ["job.json"], "the bag to be removed", 30)
    dataset = node.jobs.get(job.id).to_json()["dataset"]
    assert dataset["error"].startswith("cas is out")
    assert "next_attempt_ns" not in dataset
