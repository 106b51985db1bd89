"""Ingest jobs killed (kill -9) or cut by a power loss at chosen points, then resumed: every
record committed exactly once and the dataset advertised once, from the node's files as the
crash left them."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from services.storage.ingest import Job
from services.storage.staging import SPOOL_FORMAT
from tests.bagfactory import START_NS
from tests.unit.services.ledger.crash import output_of_killed
from tests.unit.services.storage.synced_files import synced
from tests.unit.services.storage.test_ingest import Node

IMU_RECORDS = 160
"""The IMU messages of ``bag(..., 200)``, the only topic the jobs here bind."""

KILLED_COMMITTING = """
import os, signal, sys
from pathlib import Path

root = Path(sys.argv[1])
os.environ["ROBOCLOUD_TEST_SYNC_LOG"] = str(root / "synced.jsonl")
from services.storage import staging
from services.storage.recordstore import RecordStore
from tests.unit.services.storage import synced_files
from tests.unit.services.storage.test_ingest import Node, authorship, bag

context = staging._context
staging._context = lambda: synced_files.preloaded(context())
node = Node(root / "node")
node.bindings.bind(template_id=node.approve("sensor_msgs/msg/Imu"), msgtype="sensor_msgs/msg/Imu")
append = RecordStore.append_prepared
batches = []

def dying(self, *args, **kwargs):
    batches.append(append(self, *args, **kwargs))
    if len(batches) == 2:
        os.kill(os.getpid(), signal.SIGKILL)
    return batches[-1]

RecordStore.append_prepared = dying
job = node.jobs.submit(bag(root, "b", 200), "upload:b", authorship())
print(job.id, flush=True)
node.jobs.wait(job.id, 120)
"""
"""Ingests a bag of 160 IMU records in batches of 50, killed after its second batch, having
noted what each fsync put on the disk, in the service and in its staging processes."""


def run_killed(script: str, root: Path, *args: str) -> str:
    """Run ``script`` on ``root`` until it kills itself; the job id it printed."""
    return output_of_killed(script, root, *args).split()[0]


def cut_to_synced(directory: Path, synced: dict[str, int | list[str]]) -> None:
    """Leave of ``directory``'s files what a power cut leaves: the names its last fsync saw,
    each as long as its own last fsync made it."""
    names = synced.get(str(directory.resolve()), [])
    assert isinstance(names, list)
    for file in directory.iterdir():
        size = synced.get(str(file.resolve()), 0)
        assert isinstance(size, int)
        if file.name in names:
            os.truncate(file, size)
        else:
            file.unlink()


def lose_last_page(directory: Path) -> None:
    """Cut each file's last page, as a power cut does to a file whose sync never came."""
    for file in directory.iterdir():
        size = file.stat().st_size
        os.truncate(file, (size - 1) // 4096 * 4096 if size else 0)


def assert_imu_records_once(node: Node, template_id: str) -> None:
    """The bag's IMU records in the log, each once and in the bag's order."""
    assert node.logs.size(template_id) == IMU_RECORDS
    times = [json.loads(e.record)["t"] for e in node.logs.entries(template_id, 0, IMU_RECORDS)]
    assert times == sorted(set(times))
    assert times[0] == START_NS


def named_as_format_1(directory: Path) -> None:
    """Name the spool's files as the node staged them before :data:`SPOOL_FORMAT` 2."""
    for file in directory.iterdir():
        file.rename(file.with_name(file.name.removesuffix(f".v{SPOOL_FORMAT}")))


@pytest.mark.parametrize("loss", ["unsynced", "last_page", "older_format"])
def test_a_power_cut_while_committing_resumes_with_each_record_once(
    tmp_path: Path, loss: str, caplog: pytest.LogCaptureFixture
) -> None:
    """The spool is synced before job.json says its records are staged, so a power cut after
    two batches leaves it whole ("unsynced": job.json once lived beside a spool that came
    back empty, and every resume failed). And a spool damaged all the same ("last_page"), or
    staged by a node of an older spool format ("older_format", resumed after an upgrade), is
    staged again from the bag, the commit going on past the records already committed."""
    job_id = run_killed(KILLED_COMMITTING, tmp_path)
    staged = tmp_path / "node" / "jobs" / job_id / "staged"
    state = json.loads((staged.parent / "job.json").read_text())
    assert (state["status"], state["staged"]) == ("committing", {"imu@1": IMU_RECORDS})
    if loss == "unsynced":
        cut_to_synced(staged, synced(tmp_path / "synced.jsonl"))
    elif loss == "last_page":
        lose_last_page(staged)
    else:
        named_as_format_1(staged)
    node = Node(tmp_path / "node")
    try:
        job = node.jobs.wait(job_id, 60)
        assert job.status == "succeeded", job.error
        assert job.records_committed == IMU_RECORDS
        assert_imu_records_once(node, "imu@1")
        assert ("staging again" in caplog.text) == (loss != "unsynced")
    finally:
        node.close()


class ChainPublisher:
    """Advertises on a chain kept in a file, an advertisement a line, and, as a publisher
    must, looks there first when an earlier attempt of the job's was cut short."""

    def __init__(self, chain: Path, advertised: Callable[[], None] | None = None) -> None:
        self.chain = chain
        self.advertised = advertised
        """Called once the advertisement is on the chain, before it is returned."""

    def __call__(
        self, job: Job, bag: Path, save_advertise_tx: Callable[[dict[str, Any]], None]
    ) -> dict[str, Any]:
        made = [ad for ad in self.advertisements() if ad["cid"] == job.bag]
        if made and job.publish_attempts > 1:
            return made[0]
        if not bag.exists():
            raise FileNotFoundError(bag)
        advertisement = {"cid": job.bag, "tx": f"0x{len(self.advertisements()) + 1:02x}"}
        with self.chain.open("a") as chain:
            chain.write(json.dumps(advertisement) + "\n")
        if self.advertised is not None:
            self.advertised()
        return advertisement

    def advertisements(self) -> list[dict[str, Any]]:
        if not self.chain.exists():
            return []
        return [json.loads(line) for line in self.chain.read_text().splitlines()]


KILLED_PUBLISHING = """
import os, signal, sys
from pathlib import Path
from services.storage import ingest
from tests.unit.services.storage.test_ingest import Node, authorship, bag
from tests.unit.services.storage.test_ingest_crashes import ChainPublisher

root, kill = Path(sys.argv[1]), sys.argv[2]

def die():
    os.kill(os.getpid(), signal.SIGKILL)

publisher = ChainPublisher(root / "chain.txt", die if kill == "advertised" else None)
node = Node(root / "node", publish=publisher)
node.bindings.bind(template_id=node.approve("sensor_msgs/msg/Imu"), msgtype="sensor_msgs/msg/Imu")
remove = ingest._remove

def removing(path):
    if kill == "published":
        die()
    remove(path)
    die()

ingest._remove = removing
job = node.jobs.submit(bag(root, "b", 200), "upload:b", authorship())
print(job.id, flush=True)
node.jobs.wait(job.id, 120)
"""
"""Ingests a bag of 160 IMU records and publishes it, killed at ``argv[2]``: once advertised
("advertised"), once the job saved what it published ("published"), once the bag is removed
("bag_removed")."""


@pytest.mark.parametrize("kill", ["advertised", "published", "bag_removed"])
def test_a_job_killed_while_publishing_advertises_its_dataset_once(
    tmp_path: Path, kill: str
) -> None:
    """A kill -9 after the advertisement: the resumed job advertised again (the job saved
    nothing of its publishing until it succeeded), or, with its bag removed, failed to publish
    what was advertised. Now it saves its attempt before publishing and the outcome after,
    while the bag is there; resumed, it publishes nothing again and needs no bag."""
    job_id = run_killed(KILLED_PUBLISHING, tmp_path, kill)
    chain = ChainPublisher(tmp_path / "chain.txt")
    advertised = chain.advertisements()
    assert len(advertised) == 1
    node = Node(tmp_path / "node", publish=chain)
    try:
        job = node.jobs.wait(job_id, 60)
        assert job.status == "succeeded", job.error
        assert chain.advertisements() == advertised
        assert job.dataset == advertised[0]
        assert job.publish_attempts == (2 if kill == "advertised" else 1)
        assert_imu_records_once(node, "imu@1")
        assert [path.name for path in (node.root / "jobs" / job_id).iterdir()] == ["job.json"]
    finally:
        node.close()
