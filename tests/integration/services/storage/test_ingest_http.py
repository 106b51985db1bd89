"""Bag ingestion through a real storage process and the SDK: upload, job progress, export read
back with the mcap library; bad bags, unsigned writes and unknown jobs."""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import signal
import socket
import struct
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path
from typing import Any

import anyio
import httpx
import pytest
from mcap.reader import make_reader
from rosbags.rosbag1 import Writer as Rosbag1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Rosbag2Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from robocloud.client import ServiceClient
from robocloud.errors import ApiError
from robocloud.identity import Identity
from robocloud.ingest import Ingest
from robocloud.ledger import LedgerService
from robocloud.storage import Storage as StorageClient
from robocloud.unixfs import import_bytes
from services.storage.bags import MAX_CHUNK_BYTES
from services.storage.ingest import MAX_WAITERS_PER_JOB
from services.storage.matcher import draft_template
from tests.bagfactory import (
    PERIOD_NS,
    START_NS,
    fanout_store,
    imu,
    typestore_for,
    write_bag,
    write_flags_bag,
    write_mcap_bomb,
    write_ros1_big_chunk,
)
from tests.conftest import ServiceFactory
from tests.integration.services.common.test_framework import signed_headers
from tests.long_polls import crowd_of_waits
from tests.procs import SHARED_DATA, ServiceProcess, memory_kib
from tests.raw_http import read_answer
from tests.waiting import wait_for


class Storage(ServiceClient):
    default_service = "storage"


def failure(job: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    """The error code and details of ``job``, which must have failed."""
    assert job["status"] == "failed", job
    return job["error"]["code"], job["error"]["details"]


def approve(client: Storage, msgtype: str) -> str:
    return approved(client, draft_template(typestore_for("ros1"), msgtype))


def approved(client: Storage, document: dict[str, Any]) -> str:
    """Create, submit and approve the template ``document``: its id."""
    created = client.post_json("/v1/templates", document)
    template_id = f"{created['name']}@{created['version']}"
    client.post_json(f"/v1/templates/{template_id}/submit")
    client.post_json(f"/v1/templates/{template_id}/review", {"decision": "approve"})
    return template_id


@pytest.fixture
def storage(service_factory: ServiceFactory) -> ServiceProcess:
    return service_factory("storage", {"ROBOCLOUD_STORAGE_INGEST_BATCH_RECORDS": "16"})


def test_ingest_a_bag_and_export_it(
    storage: ServiceProcess, identity: Identity, tmp_path: Path
) -> None:
    bag = write_bag(tmp_path / "run.bag", "ros1", 50, start_ns=START_NS)
    with Storage(storage.url, identity) as client, Ingest(storage.url, identity) as ingest:
        imu = approve(client, "sensor_msgs/msg/Imu")
        ingest.bind(imu, msgtype="sensor_msgs/msg/Imu")
        job = ingest.upload(bag)
        assert job["status"] in ("queued", "staging", "committing", "succeeded")
        assert job["signer"] == identity.address
        seen: list[dict[str, Any]] = []
        done = ingest.wait(job["id"], seen.append, timeout_s=120)
        assert done["status"] == "succeeded", done["error"]
        assert done["messages"] == {"done": 40, "total": 40}
        assert done["records"] == {"staged": 40, "committed": 40}
        assert sorted(done["unbound_topics"]) == ["/camera/image_raw", "/gps"]
        assert done["record_ids"] == {imu: ["imu-1-0", "imu-1-39"]}
        assert seen[-1] == done
        mcap_path = tmp_path / "out.mcap"
        ingest.export({"template": imu, "format": "mcap"}, mcap_path)
        jsonl_path = tmp_path / "out.jsonl"
        ingest.export({"template": imu, "format": "jsonl"}, jsonl_path)
    records = [json.loads(line) for line in jsonl_path.read_text().splitlines()]
    assert len(records) == 40
    assert records[0]["t"] == START_NS
    assert records[0]["robot"] == identity.address
    assert records[0]["data"]["frame_id"] == "imu_link"
    reader = make_reader(io.BytesIO(mcap_path.read_bytes()))
    from_mcap = [json.loads(message.data) for _, _, message in reader.iter_messages()]
    assert from_mcap == records
    params = {"template": imu, "format": "mcap"}
    answered = httpx.get(f"{storage.url}/v1/export", params=params, timeout=30)
    assert answered.headers["content-type"] == "application/vnd.mcap"
    assert answered.content == mcap_path.read_bytes()


def queued_behind_a_long_job(
    storage: ServiceProcess, identity: Identity, tmp_path: Path
) -> tuple[dict[str, Any], dict[str, Any]]:
    """A job of 20,000 IMU messages (about 5 s), and a small one queued behind it."""
    long_bag = write_bag(tmp_path / "long.bag", "ros1", 20_000, image_every=1_000_000)
    with Storage(storage.url, identity) as client, Ingest(storage.url, identity) as ingest:
        imu = approve(client, "sensor_msgs/msg/Imu")
        ingest.bind(imu, msgtype="sensor_msgs/msg/Imu")
        first = ingest.upload(long_bag)
        return first, ingest.upload(write_bag(tmp_path / "run.bag", "ros1", 50))


def test_a_job_waiting_its_turn_is_read_once_until_it_changes(
    storage: ServiceProcess, identity: Identity, tmp_path: Path
) -> None:
    """A robot following its job asked four times a second, a line in the node's log each
    time, for as long as the job ran or waited its turn. Each read is now a long poll
    answered when the job changes: a job queued behind a long one is read when it comes and
    when its turn does, however long it waits, and its end is seen as it comes."""
    first, second = queued_behind_a_long_job(storage, identity, tmp_path)
    with Ingest(storage.url, identity) as ingest:
        seen: list[tuple[float, dict[str, Any]]] = []
        done = ingest.wait(second["id"], lambda job: seen.append((time.monotonic(), job)))
        first_done = ingest.job(first["id"])
    assert (first_done["status"], done["status"]) == ("succeeded", "succeeded"), done["error"]
    queued = [at for at, job in seen if job["status"] == "queued"]
    turn_at, turn = next((at, job) for at, job in seen if job["status"] != "queued")
    assert turn["updated_ns"] >= first_done["updated_ns"]  # its turn came after the first
    assert turn_at - queued[0] > 1.0  # long enough for polls four times a second
    assert len(queued) <= 2  # when it came, and when the worker took it
    updates = [job["updated_ns"] for _, job in seen]
    assert updates == sorted(set(updates))  # no read without a change


def test_a_read_waiting_on_a_job_is_answered_when_the_node_stops(
    storage: ServiceProcess, identity: Identity, tmp_path: Path
) -> None:
    """uvicorn lets requests in flight finish, 5 s at most, before the app hears of a stop:
    a read waiting on a job queued behind a long one is answered, unchanged, as soon as the
    node is told to stop."""
    _, queued = queued_behind_a_long_job(storage, identity, tmp_path)
    with Ingest(storage.url, retries=0) as reader, ThreadPoolExecutor(1) as pool:
        waiting = pool.submit(reader.job, queued["id"], after_ns=queued["updated_ns"], wait_s=25)
        time.sleep(0.5)
        assert not waiting.done()
        assert storage.process is not None
        storage.process.terminate()
        stopped_at = time.monotonic()
        answer = waiting.result(timeout=20)
        answered_s = time.monotonic() - stopped_at
    assert (answer["status"], answer["updated_ns"]) == ("queued", queued["updated_ns"])
    assert answered_s < 3


def test_waits_past_a_jobs_bound_answer_at_once_and_the_rest_when_it_changes(
    storage: ServiceProcess, identity: Identity, tmp_path: Path
) -> None:
    """Waits on one job are bounded (``MAX_WAITERS_PER_JOB``): past them a read answers at
    once, as if it had not asked to wait; the others answer when the job's turn comes."""
    _, queued = queued_behind_a_long_job(storage, identity, tmp_path)
    extra = 4
    params = {"after_ns": queued["updated_ns"], "wait_s": 25}
    crowd = partial(crowd_of_waits, storage.url, f"/v1/jobs/{queued['id']}", params)
    early, woken = anyio.run(crowd, MAX_WAITERS_PER_JOB, extra)
    assert [(job["status"], job["updated_ns"]) for job in early] == [
        ("queued", queued["updated_ns"])
    ] * extra
    assert len(woken) == MAX_WAITERS_PER_JOB
    assert all(job["updated_ns"] > queued["updated_ns"] for job in woken)


@pytest.mark.parametrize(
    ("params", "field"),
    [
        ({"wait_s": "25.5", "after_ns": "1"}, "query.wait_s"),
        ({"wait_s": "-1", "after_ns": "1"}, "query.wait_s"),
        ({"wait_s": "soon", "after_ns": "1"}, "query.wait_s"),
        ({"wait_s": "5"}, "query.after_ns"),
        ({"wait_s": "5", "after_ns": "-1"}, "query.after_ns"),
        ({"wait_s": "5", "after_ns": str(2**63)}, "query.after_ns"),
    ],
)
def test_a_jobs_wait_out_of_bounds_is_refused_naming_it(
    storage: ServiceProcess, params: dict[str, str], field: str
) -> None:
    started = time.monotonic()
    response = httpx.get(f"{storage.url}/v1/jobs/{'0' * 24}", params=params, timeout=30)
    assert response.status_code == 422, response.text
    assert response.json()["error"]["details"]["errors"][0]["field"] == field
    assert time.monotonic() - started < 5


def test_bad_bags_fail_without_records(
    storage: ServiceProcess, identity: Identity, tmp_path: Path
) -> None:
    bag = write_bag(tmp_path / "run.bag", "ros1", 3000, start_ns=START_NS)
    truncated = tmp_path / "cut.bag"
    truncated.write_bytes(bag.read_bytes()[: bag.stat().st_size // 2])
    text = tmp_path / "notes.txt"
    text.write_text("hello\n")
    incoming = storage.data_dir / "ingest" / "incoming"
    with Storage(storage.url, identity) as client, Ingest(storage.url, identity) as ingest:
        imu = approve(client, "sensor_msgs/msg/Imu")
        ingest.bind(imu, msgtype="sensor_msgs/msg/Imu")
        with pytest.raises(ApiError) as not_a_bag:
            ingest.upload(text)
        assert not_a_bag.value.status == 400
        assert not_a_bag.value.code == "invalid_bag"
        # The node's name for the upload ("upload", "bag.bag") was never the robot's.
        assert not_a_bag.value.details == {"file": None, "offset": None}
        assert not_a_bag.value.message == (
            "the bag: not a ROS 1 bag, an MCAP file or a rosbag2 sqlite3 file"
        )
        assert list(incoming.iterdir()) == []
        failed = ingest.wait(ingest.upload(truncated)["id"], timeout_s=120)
        # Each accepted upload left its spool directory behind, empty.
        assert list(incoming.iterdir()) == []
        assert failed["status"] == "failed"
        assert failed["error"]["code"] == "bag_corrupt"
        assert str(storage.data_dir) not in failed["error"]["message"]  # was the spool path
        assert failed["error"]["resumable"] is False
        assert failed["records"]["committed"] == 0
        page = client.get_json("/v1/records", params={"template": imu})
        assert page["records"] == []
        with pytest.raises(ApiError) as unknown:
            ingest.job("f" * 24)
        assert unknown.value.status == 404
        assert unknown.value.code == "job_not_found"
        with pytest.raises(ApiError) as bad_binding:
            ingest.bind("Not-A-Template", topic="/imu")
        assert bad_binding.value.code == "invalid_binding"
        assert bad_binding.value.details == {"field": "template"}
    unsigned = httpx.post(
        f"{storage.url}/v1/ingest",
        content=bag.read_bytes()[:100],
        headers={"Content-Type": "application/octet-stream"},
    )
    assert unsigned.status_code == 401
    assert unsigned.json()["error"]["code"]


def test_an_mcap_cut_after_its_magic_fails_as_a_corrupt_bag(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    """With staging processes the bag is opened unchecked; rosbags raised TypeError on the
    missing first record, and the job failed as ingest_failed with that TypeError's text."""
    storage = service_factory("storage", {"ROBOCLOUD_STORAGE_INGEST_WORKERS": "2"})
    cut = tmp_path / "cut.mcap"
    cut.write_bytes((SHARED_DATA / "mcap" / "rosbag2_cpp_only_topics.mcap").read_bytes()[:8])
    with Ingest(storage.url, identity) as ingest:
        failed = ingest.wait(ingest.upload(cut)["id"], timeout_s=60)
    assert failed["status"] == "failed"
    error = failed["error"]
    assert (error["code"], error["details"], error["resumable"]) == (
        "bag_corrupt",
        {"file": None, "offset": None},
        False,
    )
    assert error["message"] == (
        "the bag: damaged or truncated "
        "(TypeError: ord() expected a character, but string of length 0 found)"
    )
    assert failed["records"] == {"staged": 0, "committed": 0}


@pytest.mark.parametrize("kind", ["mcap", "ros1"])
def test_a_decompression_bomb_fails_its_job_naming_the_chunk_and_stores_nothing(
    storage: ServiceProcess, identity: Identity, tmp_path: Path, kind: str
) -> None:
    """32 KiB of MCAP declaring a 1 GiB zstd chunk took the service to 2.1 GiB; a ROS 1
    chunk past the limit (rosbags decompresses it whole) is refused the same way."""
    if kind == "mcap":
        bag = tmp_path / "bomb.mcap"
        offset = write_mcap_bomb(bag)
        reason = f"chunk declares {1 << 30} bytes decompressed, more than the"
    else:
        bag = write_ros1_big_chunk(tmp_path / "big.bag", MAX_CHUNK_BYTES)
        offset = 13 + 4096
        reason = f"chunk decompresses to more than {MAX_CHUNK_BYTES} bytes (lz4)"
    with Storage(storage.url, identity) as client, Ingest(storage.url, identity) as ingest:
        text = approve(client, "std_msgs/msg/String")
        ingest.bind(text, msgtype="std_msgs/msg/String")
        failed = ingest.wait(ingest.upload(bag)["id"], timeout_s=120)
        error = failed["error"]
        assert failure(failed) == ("bag_unreadable", {"file": None, "offset": offset})
        assert error["message"].startswith(f"the bag at byte {offset}: {reason}")
        assert failed["records"] == {"staged": 0, "committed": 0}
        assert client.get_json("/v1/records", params={"template": text})["records"] == []


def test_a_real_recording_is_ingested_through_the_draft_its_job_proposes(
    storage: ServiceProcess, identity: Identity
) -> None:
    """cartographer's tiny bag (2014, so ``t`` is past 2**53): ingest, take the draft the job
    proposes for ``/imu``, approve and bind it, ingest again, query one second of it."""
    bag = SHARED_DATA / "rosbag1" / "cartographer_b0-2014-07-21-12-42-53-tiny.bag"
    with (
        StorageClient(storage.url, identity) as records,
        Ingest(storage.url, identity) as ingest,
    ):
        first = ingest.wait(ingest.upload(bag)["id"], timeout_s=120)
        assert first["status"] == "succeeded", first["error"]
        assert sorted(first["unbound_topics"]) == ["horizontal_laser_2d", "imu"]
        assert first["records"]["committed"] == 0
        draft = next(t["draft"] for t in first["topics"] if t["topic"] == "imu")
        created = records.create_template(draft)
        records.submit_template(created.id)
        records.review_template(created.id, "approve", "cartographer's IMU")
        ingest.bind(created.id, topic="/imu")

        second = ingest.wait(ingest.upload(bag)["id"], timeout_s=120)
        assert second["status"] == "succeeded", second["error"]
        assert second["records"]["committed"] == 1243
        assert second["unbound_topics"] == ["horizontal_laser_2d"]
        start = 1_405_946_575_000_000_000
        page = records.query(template=created.id, start=start, end=start + 10**9, limit=1000)
    times = [stored.record["t"] for stored in page.records]
    assert times == sorted(times)
    assert 150 < len(times) < 250  # the IMU runs near 200 Hz
    assert all(start <= t < start + 10**9 for t in times)
    assert page.records[0].record["data"]["frame_id"]


def write_fanout_mcap(directory: Path, width: int, levels: int = 7) -> Path:
    """A bare MCAP file (about 8 KB for 16 fields a level) with ``/fan``, a connection of
    ``fan_msgs/msg/Level0`` and no message, whose definition nests ``levels`` types of
    ``width`` message fields each (``width ** (levels + 1)`` leaves drafted whole), and
    ``/chatter``, one ``std_msgs/msg/String``."""
    store = fanout_store(width, levels, Stores.ROS2_HUMBLE)
    string = "std_msgs/msg/String"
    with Rosbag2Writer(directory, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        writer.add_connection("/fan", "fan_msgs/msg/Level0", typestore=store)
        chatter = writer.add_connection("/chatter", string, typestore=store)
        message = store.types[string](data="hello")
        writer.write(chatter, START_NS, store.serialize_cdr(message, string))
    return next(directory.glob("*.mcap"))


def test_a_schema_whose_draft_fans_out_leaves_the_ingest_worker_free(
    storage: ServiceProcess, identity: Identity, tmp_path: Path
) -> None:
    """A topic bound to no template gets a draft of its definition, which expanded every
    nested type wherever it is used: eight lines of 16 fields (16**8 leaves) in an 8 KB
    upload held the only ingest thread for good, the job queued and the service's memory
    growing. The draft stops past the fields a template may hold; the job goes on."""
    bag = write_fanout_mcap(tmp_path / "fan", 16)
    assert bag.stat().st_size < 16 * 1024
    with Ingest(storage.url, identity) as ingest:
        done = ingest.wait(ingest.upload(bag)["id"], timeout_s=30)
        assert done["status"] == "succeeded", done
        topics = {topic["topic"]: topic for topic in done["topics"]}
        assert topics["/fan"]["msgtype"] == "fan_msgs/msg/Level0"
        assert topics["/fan"]["draft"] is None
        assert topics["/chatter"]["draft"]["fields"] == {"data": "string"}
        assert sorted(done["unbound_topics"]) == ["/chatter", "/fan"]
        assert done["records"] == {"staged": 0, "committed": 0}
        again = ingest.wait(ingest.upload(bag)["id"], timeout_s=30)
        assert again["status"] == "succeeded", again


def test_a_fixed_array_rosbags_would_unroll_without_end_disables_only_its_topic(
    storage: ServiceProcess, identity: Identity, tmp_path: Path
) -> None:
    """``string[100000000] names`` in a 2 KB MCAP of no such message: opening the bag had
    rosbags generate a line of code per element (129 s and 3.9 GiB for 100,000), so the job
    stayed queued, the only ingest thread held and the service's memory growing. Its topic
    now has the problem, bound it fails its job as undefined, and the bag's others stage."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg("string[100000000] names", "wide_msgs/msg/Names"))
    string = "std_msgs/msg/String"
    with Rosbag2Writer(tmp_path / "wide", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        writer.add_connection("/names", "wide_msgs/msg/Names", typestore=store)
        chatter = writer.add_connection("/chatter", string, typestore=store)
        message = store.types[string](data="hello")
        writer.write(chatter, START_NS, store.serialize_cdr(message, string))
    bag = next((tmp_path / "wide").glob("*.mcap"))
    with Storage(storage.url, identity) as client, Ingest(storage.url, identity) as ingest:
        text = approve(client, string)
        ingest.bind(text, topic="/chatter")
        done = ingest.wait(ingest.upload(bag)["id"], timeout_s=30)
        assert done["status"] == "succeeded", done
        assert done["unbound_topics"] == ["/names"]
        assert next(t for t in done["topics"] if t["topic"] == "/names")["draft"] is None
        assert done["records"] == {"staged": 1, "committed": 1}
        ingest.bind(text, topic="/names")
        failed = ingest.wait(ingest.upload(bag)["id"], timeout_s=30)
    error = failed["error"]
    assert failure(failed) == (
        "message_type_undefined",
        {"topic": "/names", "msgtype": "wide_msgs/msg/Names"},
    )
    reason = "holds 100000000 elements of fixed-size arrays of strings or messages"
    assert reason in error["message"]
    assert failed["records"] == {"staged": 0, "committed": 0}


ITEMS = "hollow_msgs/msg/Items"


def test_a_sequence_of_empty_messages_disables_only_its_topic(
    storage: ServiceProcess, identity: Identity, tmp_path: Path
) -> None:
    """In ROS 1 ``std_msgs/Empty`` serialises to no bytes, so one 8-byte message of ``int32
    seq`` and ``std_msgs/Empty[] items`` whose length says 0xFFFFFFFF had staging create 4.3
    billion objects (the service's memory), its topic bound to a template of ``seq`` alone.
    The definition has its problem from the bag's open: bound, the job fails as undefined
    and stores nothing; the bag's other topic stages."""
    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg("int32 seq\nstd_msgs/Empty[] items", ITEMS))
    string = "std_msgs/msg/String"
    bag = tmp_path / "hollow.bag"
    with Rosbag1Writer(bag) as writer:
        items = writer.add_connection("/items", ITEMS, typestore=store)
        chatter = writer.add_connection("/chatter", string, typestore=store)
        writer.write(items, START_NS, struct.pack("<iI", 7, 0xFFFFFFFF))
        hello = store.serialize_ros1(store.types[string](data="hello"), string)
        writer.write(chatter, START_NS + 1, hello)
    with Storage(storage.url, identity) as client, Ingest(storage.url, identity) as ingest:
        ingest.bind(approve(client, string), topic="/chatter")
        done = ingest.wait(ingest.upload(bag)["id"], timeout_s=30)
        assert done["status"] == "succeeded", done
        assert done["unbound_topics"] == ["/items"]
        assert done["records"] == {"staged": 1, "committed": 1}
        seq = approved(client, {"name": "item_seq", "version": 1, "fields": {"seq": "int"}})
        ingest.bind(seq, topic="/items")
        failed = ingest.wait(ingest.upload(bag)["id"], timeout_s=30)
    error = failed["error"]
    assert failure(failed) == ("message_type_undefined", {"topic": "/items", "msgtype": ITEMS})
    reason = (
        "the bag's definition holds hollow_msgs/msg/Items.items, an array of a message that "
        "serialises to no bytes in ROS 1"
    )
    assert reason in error["message"]
    assert failed["records"] == {"staged": 0, "committed": 0}
    with StorageClient(storage.url, identity) as records:
        assert records.query(template=seq, limit=10, cursor=None).records == []


def test_a_message_decoding_past_a_staging_process_memory_fails_its_job_alone(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    """A ROS 1 ``std_msgs/Bool[]`` decodes to a Python object of about 100 bytes per byte: 8
    MB of it to some 800 MB, which staging in the service's process took from the service.
    Its staging process runs out of its address space instead: the job fails naming the
    message, stores nothing, and the service, which never held it, ingests the next bag."""
    storage = service_factory(
        "storage", {"ROBOCLOUD_STORAGE_INGEST_WORKER_MEMORY_BYTES": str(384 * 1024**2)}
    )
    flags = 8 * 1024**2
    bag = write_flags_bag(tmp_path / "flags.bag", flags, chatter="hello")
    with Storage(storage.url, identity) as client, Ingest(storage.url, identity) as ingest:
        text = approve(client, "std_msgs/msg/String")
        seq = approved(client, {"name": "flag_seq", "version": 1, "fields": {"seq": "int"}})
        ingest.bind(text, topic="/chatter")
        ingest.bind(seq, topic="/flags")
        failed = ingest.wait(ingest.upload(bag)["id"], timeout_s=120)
        error = failed["error"]
        assert failure(failed) == (
            "message_too_large",
            {"topic": "/flags", "t": START_NS + 1, "bytes": flags + 8},
        )
        assert error["message"] == (
            f"topic '/flags' at t={START_NS + 1}: its {flags + 8}-byte message decodes to more "
            "than a staging process may hold (ROBOCLOUD_STORAGE_INGEST_WORKER_MEMORY_BYTES)"
        )
        assert failed["records"] == {"staged": 0, "committed": 0}
        for template in (text, seq):
            assert client.get_json("/v1/records", params={"template": template})["records"] == []
        assert memory_kib(storage)["VmHWM"] < 384 * 1024

        small = write_flags_bag(tmp_path / "small.bag", 16, chatter="hello")
        done = ingest.wait(ingest.upload(small)["id"], timeout_s=60)
        assert done["status"] == "succeeded", done["error"]
        stored = client.get_json("/v1/records", params={"template": text})["records"]
    assert [r["record"]["data"] for r in stored] == [{"data": "hello"}]


def storage_address(storage: ServiceProcess) -> str:
    return str(httpx.get(f"{storage.url}/v1/node", timeout=10).json()["address"])


def _publish_an_imu_bag(
    storage: ServiceProcess, ledger: ServiceProcess, identity: Identity, tmp_path: Path
) -> tuple[Path, str, dict[str, Any]]:
    """Ingest a bag of IMU messages and check its dataset was advertised by the node: the bag,
    the IMU template's id and the job's dataset."""
    bag = write_bag(tmp_path / "run.bag", "ros1", 50, start_ns=START_NS)
    with StorageClient(storage.url, identity) as records, Ingest(storage.url, identity) as ingest:
        imu = approve(records, "sensor_msgs/msg/Imu")
        ingest.bind(imu, msgtype="sensor_msgs/msg/Imu")
        job = ingest.wait(ingest.upload(bag)["id"], timeout_s=180)
    assert job["status"] == "succeeded", job["error"]
    dataset: dict[str, Any] = job["dataset"]
    assert set(dataset) == {"cid", "description", "tx"}, dataset
    with LedgerService(ledger.url) as service:
        (advertised,) = service.advertisements(cid=dataset["cid"])
    assert advertised.description == dataset["description"]
    assert advertised.advertiser == storage_address(storage)
    return bag, imu, dataset


def publishing_node(service_factory: ServiceFactory) -> tuple[ServiceProcess, ServiceProcess]:
    """A ledger, and a storage node publishing its datasets to cas and the ledger (the
    knowledge follower off)."""
    ledger = service_factory("ledger")
    storage = service_factory(
        "storage",
        {
            "ROBOCLOUD_LEDGER_URL": ledger.url,
            "ROBOCLOUD_CAS_URL": service_factory("cas").url,
            "ROBOCLOUD_KNOWLEDGE_FOLLOW_LEDGER": "false",
        },
    )
    return ledger, storage


def test_an_ingested_bag_is_described_indexed_and_advertised(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    ledger, storage = publishing_node(service_factory)
    bag, imu, dataset = _publish_an_imu_bag(storage, ledger, identity, tmp_path)
    assert dataset["cid"] == str(import_bytes(bag.read_bytes())[1])
    ((_, count, epoch, root),) = ingestions(storage, dataset["cid"])
    assert count == 40
    manifest = httpx.get(f"{storage.url}/v1/epochs/{epoch}", timeout=10).json()
    assert manifest["tmt_root"] == root
    assert manifest["heads"] == [
        {"template": imu, "size": 40, "root": manifest["heads"][0]["root"]}
    ]


def ingestions(storage: ServiceProcess, bag_cid: str) -> list[tuple[str, int, int, str]]:
    """Each ingestion of the bag the knowledge base holds: its job, record count, epoch and
    TMT root, by job."""
    query = f"""
        PREFIX rc: <https://w3id.org/robocloud#>
        PREFIX dcterms: <http://purl.org/dc/terms/>
        SELECT ?job ?count ?epoch ?root WHERE {{
            <ipfs://{bag_cid}> rc:ingestion ?ingestion .
            ?ingestion dcterms:identifier ?job ; rc:recordCount ?count ; rc:epoch ?epoch ;
                rc:tmtRoot ?root
        }} ORDER BY ?job
    """
    return [
        (
            row["job"]["value"],
            int(row["count"]["value"]),
            int(row["epoch"]["value"]),
            row["root"]["value"],
        )
        for row in sparql_rows(storage, query)
    ]


def sparql_rows(storage: ServiceProcess, query: str) -> list[dict[str, Any]]:
    """The bindings of a SELECT on the node's knowledge base, as SPARQL JSON results."""
    answer = httpx.get(
        f"{storage.url}/v1/knowledge/sparql",
        params={"query": query},
        headers={"Accept": "application/sparql-results+json"},
        timeout=30,
    ).json()
    rows: list[dict[str, Any]] = answer["results"]["bindings"]
    return rows


def test_a_ros1_bag_naming_topics_without_a_slash_is_published_with_its_records_topics(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    """evo's example bag (SOURCES.md) names its topics ``groundtruth`` and ``ORB-SLAM``. Its
    records hold ``/groundtruth``, but the dataset's description named ``groundtruth``,
    which the knowledge base's shape refuses: the records were stored and the dataset never
    published. Its topics are now named as its records hold them, and found so."""
    _, storage = publishing_node(service_factory)
    store = typestore_for("ros1")
    bag = tmp_path / "relative.bag"
    with Rosbag1Writer(bag) as writer:
        connection = writer.add_connection("imu", "sensor_msgs/msg/Imu", typestore=store)
        for index in range(5):
            t_ns = START_NS + index * PERIOD_NS
            raw = store.serialize_ros1(imu(store, index, t_ns), "sensor_msgs/msg/Imu")
            writer.write(connection, t_ns, raw)
    with StorageClient(storage.url, identity) as records, Ingest(storage.url, identity) as ingest:
        template = approve(records, "sensor_msgs/msg/Imu")
        ingest.bind(template, topic="imu")
        job = ingest.wait(ingest.upload(bag)["id"], timeout_s=180)
        assert job["status"] == "succeeded", job["error"]
        assert [(t["topic"], t["template"]) for t in job["topics"]] == [("imu", template)]
        assert set(job["dataset"]) == {"cid", "description", "tx"}, job["dataset"]
        found = records.query(template=template, topic="imu").records
    assert [item.record["topic"] for item in found] == ["/imu"] * 5
    query = f"""
        PREFIX rc: <https://w3id.org/robocloud#>
        SELECT ?topic WHERE {{ <ipfs://{job["dataset"]["cid"]}> rc:topic ?topic }}
    """
    assert [row["topic"]["value"] for row in sparql_rows(storage, query)] == ["/imu"]


def test_a_bag_ingested_again_for_a_topic_bound_since_keeps_each_jobs_counts_and_epoch(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    """The second job publishes a second description of the same bag: each job's record count,
    epoch and TMT root stay paired in the knowledge base (on the dataset itself they merged into
    two counts and two epochs that no query could tell apart)."""
    ledger, storage = publishing_node(service_factory)
    bag, _, dataset = _publish_an_imu_bag(storage, ledger, identity, tmp_path)
    with StorageClient(storage.url, identity) as records, Ingest(storage.url, identity) as ingest:
        gps = approve(records, "sensor_msgs/msg/NavSatFix")
        ingest.bind(gps, topic="/gps")
        again = ingest.wait(ingest.upload(bag)["id"], timeout_s=180)
        assert again["status"] == "succeeded", again["error"]
        (imu_topic,) = [topic for topic in again["topics"] if topic["topic"] == "/imu"]
        gps_count = len(records.query(template=gps, limit=100).records)
    first = imu_topic["ingested_by"]
    assert again["dataset"]["cid"] == dataset["cid"]
    assert again["dataset"]["description"] != dataset["description"]
    found = ingestions(storage, dataset["cid"])
    assert sorted((job, count) for job, count, _, _ in found) == sorted(
        [(first, 40), (again["id"], gps_count)]
    )
    for _, _, epoch, root in found:
        manifest = httpx.get(f"{storage.url}/v1/epochs/{epoch}", timeout=10).json()
        assert manifest["tmt_root"] == root
    with LedgerService(ledger.url) as service:
        advertised = service.advertisements(cid=dataset["cid"])
    assert [ad.description for ad in advertised] == [
        dataset["description"],
        again["dataset"]["description"],
    ]


def test_a_bag_sent_again_is_neither_stored_nor_advertised_twice(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    """The robot sends its bag again (its answer lost, its script run twice): the second job
    names the first for its topic and commits nothing, and the node advertises the bag once."""
    ledger, storage = publishing_node(service_factory)
    bag, imu, dataset = _publish_an_imu_bag(storage, ledger, identity, tmp_path)
    with StorageClient(storage.url, identity) as records, Ingest(storage.url, identity) as ingest:
        again = ingest.wait(ingest.upload(bag)["id"], timeout_s=180)
        assert again["status"] == "succeeded", again["error"]
        assert again["records"] == {"staged": 0, "committed": 0}
        (imu_topic,) = [topic for topic in again["topics"] if topic["topic"] == "/imu"]
        assert imu_topic["template"] == imu
        first = ingest.job(imu_topic["ingested_by"])
        assert first["id"] != again["id"]
        assert (first["bag"], first["records"]["committed"]) == (again["bag"], 40)
        assert imu_topic["skipped"] == f"ingested from this bag into {imu} by job {first['id']}"
        assert again["dataset"] is None
        assert len(records.query(template=imu, limit=100).records) == 40
    with LedgerService(ledger.url) as service:
        assert [ad.description for ad in service.advertisements(cid=dataset["cid"])] == [
            dataset["description"]
        ]


def test_a_full_knowledge_base_does_not_hold_back_the_datasets_advertisement(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    """The description is not indexed here; it is advertised, and the node's own ledger
    follower keeps it pending until there is room. Before, the dataset was never published."""
    ledger = service_factory("ledger")
    storage = service_factory(
        "storage",
        {
            "ROBOCLOUD_LEDGER_URL": ledger.url,
            "ROBOCLOUD_CAS_URL": service_factory("cas").url,
            "ROBOCLOUD_KNOWLEDGE_MAX_TOTAL_BYTES": "1",
            "ROBOCLOUD_KNOWLEDGE_POLL_S": "0.2",
        },
    )
    _publish_an_imu_bag(storage, ledger, identity, tmp_path)

    def knowledge() -> dict[str, Any]:
        return dict(httpx.get(f"{storage.url}/v1/knowledge", timeout=10).json())

    wait_for(lambda: knowledge()["ledger"]["pending"] == 1, "the follower to keep it pending")
    state = knowledge()
    assert (state["descriptions"], state["bytes"]) == (0, 0)
    assert not list((storage.data_dir / "knowledge" / "descriptions").iterdir())


def _ingest_imu_until(
    storage: ServiceProcess,
    identity: Identity,
    bag: Path,
    until: Callable[[dict[str, Any]], bool],
    what: str,
) -> tuple[str, str]:
    """Upload ``bag`` with its IMU topic bound and wait until its job is as ``until`` says:
    the template id and the job id."""
    with StorageClient(storage.url, identity) as records, Ingest(storage.url, identity) as ingest:
        imu = approve(records, "sensor_msgs/msg/Imu")
        ingest.bind(imu, msgtype="sensor_msgs/msg/Imu")
        job_id: str = ingest.upload(bag)["id"]
        wait_for(lambda: until(ingest.job(job_id)), what)
    return imu, job_id


def test_kill_9_while_committing_a_bag_ingests_it_exactly_once(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    """The service dies between two batches of a job; at the next start the job resumes and
    every message of the bound topic is a record exactly once."""
    storage = service_factory(
        "storage",
        {
            "ROBOCLOUD_STORAGE_INGEST_BATCH_RECORDS": "200",
            "ROBOCLOUD_STORAGE_ANCHOR": "false",
            "ROBOCLOUD_STORAGE_PUBLISH_DATASETS": "false",
        },
    )
    bag = write_bag(tmp_path / "run.bag", "ros1", 12_000, start_ns=START_NS)
    imu, job_id = _ingest_imu_until(
        storage,
        identity,
        bag,
        lambda job: job["records"]["committed"] > 0,
        "the job to commit its first batch",
    )
    assert storage.process is not None
    os.kill(storage.process.pid, signal.SIGKILL)
    storage.process.wait()
    storage.start()
    with StorageClient(storage.url, identity) as records, Ingest(storage.url, identity) as ingest:
        done = ingest.wait(job_id, timeout_s=300)
        assert done["status"] == "succeeded", done["error"]
        times: list[int] = []
        cursor = None
        while True:
            page = records.query(template=imu, limit=1000, cursor=cursor)
            times.extend(stored.record["t"] for stored in page.records)
            if page.next is None:
                break
            cursor = page.next
    expected = done["messages"]["total"]
    assert done["records"]["committed"] == expected
    assert len(times) == expected
    assert len(set(times)) == expected


PARALLEL = {
    "ROBOCLOUD_STORAGE_INGEST_WORKERS": "2",
    "ROBOCLOUD_STORAGE_INGEST_PARALLEL_MESSAGES": "1",
}
QUIET_NODE = {"ROBOCLOUD_STORAGE_ANCHOR": "false", "ROBOCLOUD_STORAGE_PUBLISH_DATASETS": "false"}


def _exported(storage: ServiceProcess, identity: Identity, bag: Path, out: Path) -> bytes:
    """Ingest ``bag`` (IMU and NavSatFix bound) and export every IMU record as JSON lines."""
    with Storage(storage.url, identity) as client, Ingest(storage.url, identity) as ingest:
        imu = approve(client, "sensor_msgs/msg/Imu")
        gps = approve(client, "sensor_msgs/msg/NavSatFix")
        ingest.bind(imu, msgtype="sensor_msgs/msg/Imu")
        ingest.bind(gps, msgtype="sensor_msgs/msg/NavSatFix")
        done = ingest.wait(ingest.upload(bag)["id"], timeout_s=120)
        assert done["status"] == "succeeded", done["error"]
        assert done["records"] == {"staged": 1800, "committed": 1800}
        assert done["record_ids"] == {
            imu: ["imu-1-0", "imu-1-1599"],
            gps: ["nav_sat_fix-1-0", "nav_sat_fix-1-199"],
        }
        ingest.export({"template": imu, "format": "jsonl"}, out)
    return out.read_bytes()


def test_a_bag_staged_by_worker_processes_gives_the_records_of_one_pass(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    """The same bag through a service staging it in two windows and one staging it whole in
    one process: the exported records are the same bytes, in the same order."""
    bag = write_bag(tmp_path / "run.bag", "ros1", 2000, start_ns=START_NS)
    parallel = service_factory("storage", {**PARALLEL, **QUIET_NODE})
    single = service_factory("storage", {"ROBOCLOUD_STORAGE_INGEST_WORKERS": "1", **QUIET_NODE})
    staged_apart = _exported(parallel, identity, bag, tmp_path / "parallel.jsonl")
    staged_whole = _exported(single, identity, bag, tmp_path / "single.jsonl")
    assert staged_apart.count(b"\n") == 1600
    assert staged_apart == staged_whole


def _descendants(pid: int) -> list[int]:
    found: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        for child in (task / "children").read_text().split():
            found += [int(child), *_descendants(int(child))]
    return found


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_kill_9_while_worker_processes_stage_a_bag(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    """The service dies while two processes stage a bag: they do not outlive it, and at the
    next start the job stages again and ingests every message exactly once."""
    storage = service_factory("storage", {**PARALLEL, **QUIET_NODE})
    bag = write_bag(tmp_path / "run.bag", "ros1", 60_000, start_ns=START_NS)
    imu, job_id = _ingest_imu_until(
        storage,
        identity,
        bag,
        lambda job: job["status"] == "staging" and job["messages"]["done"] > 0,
        "the workers to stage their first messages",
    )
    assert storage.process is not None
    helpers = _descendants(storage.process.pid)
    assert len(helpers) >= 3, "a forkserver and two staging processes"
    os.kill(storage.process.pid, signal.SIGKILL)
    storage.process.wait()
    wait_for(lambda: not any(_alive(pid) for pid in helpers), "the staging processes to end")
    storage.start()
    with StorageClient(storage.url, identity) as records, Ingest(storage.url, identity) as ingest:
        done = ingest.wait(job_id, timeout_s=300)
        assert done["status"] == "succeeded", done["error"]
        page = records.query(template=imu, limit=1, cursor=None)
        assert page.records[0].record["t"] == START_NS
    assert done["records"]["committed"] == done["messages"]["total"] == 48_000
    assert done["record_ids"] == {imu: ["imu-1-0", "imu-1-47999"]}


CLOUD = "sensor_msgs/msg/PointCloud"


def write_point_clouds(path: Path, count: int, points: int) -> Path:
    """A ROS 1 bag (lz4) of ``count`` ``sensor_msgs/PointCloud`` of ``points`` points at 0,
    100 ms apart: a few KiB a message on disk, where 200,000 points decode in about a third
    of a second, into as many objects."""
    store = get_typestore(Stores.ROS1_NOETIC)
    types = store.types
    stamp = types["builtin_interfaces/msg/Time"](sec=0, nanosec=0)
    header = types["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id="lidar")
    point = types["geometry_msgs/msg/Point32"](x=0.0, y=0.0, z=0.0)
    cloud = types[CLOUD](header=header, points=[point] * points, channels=[])
    raw = store.serialize_ros1(cloud, CLOUD)
    writer = Rosbag1Writer(path)
    writer.set_compression(Rosbag1Writer.CompressionFormat.LZ4)
    with writer:
        connection = writer.add_connection("/cloud", CLOUD, typestore=store)
        for index in range(count):
            writer.write(connection, START_NS + index * 100_000_000, raw)
    return path


def _children(pid: int) -> list[int]:
    return [
        int(child)
        for task in Path(f"/proc/{pid}/task").iterdir()
        for child in (task / "children").read_text().split()
    ]


def _staging_processes(service: int) -> list[int]:
    """The forkserver the service started and the processes it forked: the staging ones."""
    for pid in _children(service):
        with contextlib.suppress(FileNotFoundError):
            if b"forkserver" in Path(f"/proc/{pid}/cmdline").read_bytes():
                return [pid, *_children(pid)]
    return []


def _cpu_s(pid: int) -> float:
    """Seconds of CPU ``pid`` has used (user and system)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def test_kill_9_ends_staging_processes_in_the_midst_of_decoding(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    """A staging process writes to the service only between messages (every 1,000 or 2 s),
    so one decoding slow messages (point clouds of 200,000 points, bound to a template of
    their frame) did not learn that the service was killed: such processes ran on, at GBs of
    memory where a bag's decode was costly. They now end with it, in the midst of their
    work."""
    storage = service_factory("storage", {**PARALLEL, **QUIET_NODE})
    bag = write_point_clouds(tmp_path / "clouds.bag", 120, 200_000)
    assert bag.stat().st_size < 4 * 1024**2
    assert storage.process is not None
    service = storage.process.pid
    with Storage(storage.url, identity) as client, Ingest(storage.url, identity) as ingest:
        frame = approved(client, {"name": "cloud", "version": 1, "fields": {"frame_id": "string"}})
        ingest.bind(frame, topic="/cloud")
        job_id = ingest.upload(bag)["id"]
        helpers = wait_for(
            lambda: len(found := _staging_processes(service)) == 3 and found,
            "a forkserver and two staging processes",
        )
        before = {pid: _cpu_s(pid) for pid in helpers[1:]}
        wait_for(
            lambda: all(_cpu_s(pid) > used + 1.0 for pid, used in before.items()),
            "both staging processes to decode for a second",
        )
        job = ingest.job(job_id)
    assert job["status"] == "staging"
    assert job["messages"]["done"] < job["messages"]["total"] == 120
    os.kill(service, signal.SIGKILL)
    storage.process.wait()
    try:
        wait_for(
            lambda: not any(_alive(pid) for pid in helpers),
            "the staging processes to end with the service",
            timeout_s=5,
        )
    except AssertionError:
        for pid in helpers[1:]:  # left to decode, they would take the machine for a minute
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
        raise


def test_a_json_body_past_a_few_fields_is_refused_before_it_is_held(
    storage: ServiceProcess, identity: Identity
) -> None:
    """``/v1/ingest`` takes a bag of up to 16 GiB, or ``{"cid"}``: a JSON body under the
    bag's limit was read whole into memory, so a robot could hand the node gigabytes of it.
    Refused by its declared length before a byte is read, or while it streams in."""
    declared = f"POST /v1/ingest HTTP/1.1\r\nHost: x\r\nContent-Length: {1 << 30}\r\n"
    headers = signed_headers(identity, "/v1/ingest", b"never sent")
    assert headers["Content-Type"] == "application/json"
    head = declared + "".join(f"{name}: {value}\r\n" for name, value in headers.items())
    with socket.create_connection(("127.0.0.1", storage.port)) as sock:
        sock.sendall(head.encode() + b"\r\n")
        status, answer = read_answer(sock)
    assert (status, answer["error"]["code"]) == (413, "payload_too_large")
    assert answer["error"]["details"] == {"header": "Content-Length", "limit": 64 * 1024}
    body = b'{"cid": "' + b"b" * 100_000 + b'"}'
    with ServiceClient(storage.url, identity, retries=0) as client, pytest.raises(ApiError) as big:
        client.request(
            "POST",
            "/v1/ingest",
            content=iter([body[:50_000], body[50_000:]]),
            content_sha256=hashlib.sha256(body).hexdigest(),
            headers={"Content-Type": "application/json"},
        )
    assert (big.value.status, big.value.code) == (413, "payload_too_large")
    assert big.value.details == {"limit": 64 * 1024}
    assert [p.name for p in (storage.data_dir / "ingest").iterdir() if p.name != "incoming"] == [
        "ingested.sqlite"
    ], "no job"


def refused_for_jobs(refusal: ApiError, limit: int, per: str) -> None:
    assert (refusal.status, refusal.code) == (429, "too_many_jobs")
    assert refusal.details == {"limit": limit, "per": per, "retry_after": 5}


def test_a_bag_resent_while_its_job_runs_gets_that_job_before_its_body(
    storage: ServiceProcess, identity: Identity, tmp_path: Path
) -> None:
    """The robot's answer was lost while its long bag staged: the resend is answered with the
    running job before a byte of the bag is read again (it was received whole again, up to
    16 GiB, and its records stored twice)."""
    long_bag = write_bag(tmp_path / "long.bag", "ros1", 50_000, start_ns=START_NS)
    body = long_bag.read_bytes()
    with Storage(storage.url, identity) as client, Ingest(storage.url, identity) as ingest:
        ingest.bind(approve(client, "sensor_msgs/msg/Imu"), msgtype="sensor_msgs/msg/Imu")
        running = ingest.upload(long_bag)
        headers = signed_headers(identity, "/v1/ingest", body)
        headers["Content-Type"] = "application/octet-stream"
        head = f"POST /v1/ingest HTTP/1.1\r\nHost: x\r\nContent-Length: {len(body)}\r\n"
        head += "".join(f"{name}: {value}\r\n" for name, value in headers.items())
        with socket.create_connection(("127.0.0.1", storage.port)) as sock:
            sock.sendall(head.encode() + b"\r\n")
            status, answer = read_answer(sock)
        assert (status, answer["id"]) == (202, running["id"])
        assert answer["status"] in ("queued", "staging", "committing")
        done = ingest.wait(running["id"], timeout_s=300)
    assert (done["status"], done["records"]["committed"]) == ("succeeded", 40_000)
    jobs = [
        path.name
        for path in (storage.data_dir / "ingest").iterdir()
        if path.is_dir() and path.name != "incoming"
    ]
    assert jobs == [running["id"]]


def test_one_robot_holds_its_share_of_the_ingest_queue_and_is_refused_before_its_body(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    """Two places, one a robot: while the first robot's long bag stages, its next bag is
    refused before a byte of it is read (it was received whole, up to 16 GiB, then refused),
    a second robot still gets the other place, and a third finds the queue full."""
    storage = service_factory(
        "storage",
        {
            "ROBOCLOUD_STORAGE_MAX_INGEST_JOBS": "2",
            "ROBOCLOUD_STORAGE_MAX_INGEST_JOBS_PER_ROBOT": "1",
        },
    )
    long_bag = write_bag(tmp_path / "long.bag", "ros1", 50_000, start_ns=START_NS)
    small_bag = write_bag(tmp_path / "small.bag", "ros1", 20, start_ns=START_NS)
    second, third = Identity.generate(), Identity.generate()
    with Storage(storage.url, identity) as client, Ingest(storage.url, identity) as ingest:
        ingest.bind(approve(client, "sensor_msgs/msg/Imu"), msgtype="sensor_msgs/msg/Imu")
    with (
        Ingest(storage.url, identity, retries=0) as first_robot,
        Ingest(storage.url, second, retries=0) as second_robot,
        Ingest(storage.url, third, retries=0) as third_robot,
    ):
        running = first_robot.upload(long_bag)
        with pytest.raises(ApiError) as refused:
            first_robot.upload(small_bag)
        refused_for_jobs(refused.value, 1, "robot")
        declared = f"POST /v1/ingest HTTP/1.1\r\nHost: x\r\nContent-Length: {1 << 30}\r\n"
        headers = signed_headers(identity, "/v1/ingest", b"never sent")
        headers["Content-Type"] = "application/octet-stream"
        head = declared + "".join(f"{name}: {value}\r\n" for name, value in headers.items())
        with socket.create_connection(("127.0.0.1", storage.port)) as sock:
            sock.sendall(head.encode() + b"\r\n")
            status, answer = read_answer(sock)
        assert (status, answer["error"]["code"]) == (429, "too_many_jobs")
        queued = second_robot.upload(small_bag)
        with pytest.raises(ApiError) as full:
            third_robot.upload(small_bag)
        refused_for_jobs(full.value, 2, "service")
        assert first_robot.job(running["id"])["status"] in ("queued", "staging", "committing")
        for job in (running, queued):
            assert first_robot.wait(job["id"], timeout_s=300)["status"] == "succeeded"
        assert (
            third_robot.wait(third_robot.upload(small_bag)["id"], timeout_s=60)["status"]
            == "succeeded"
        )
    jobs = [
        path.name
        for path in (storage.data_dir / "ingest").iterdir()
        if path.is_dir() and path.name != "incoming"
    ]
    assert len(jobs) == 3, "the refused bags left nothing behind"
