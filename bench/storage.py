"""Storage benchmarks. Each part is one function; ``main`` runs them all, each printing
ratios against a baseline measured in the same run.

Proofs (engineer anchor), against a ledger and a cas started here:

1. Acknowledgement to proof: records appended (and fsynced) through the node's ``RecordLogs``
   in batches of 1,000, each batch followed by ``notify``; the time from ``append`` returning
   to the first moment its last record's proof is served (its epoch cut and anchored), p50 and
   p99, beside the epoch length (the wait the design accepts).
2. Proof fetch plus verification: ``GET /v1/records/{id}/proof`` from the storage service over
   HTTP, then ``verify_record_proof`` (hashlib, one ``eth_call`` and one
   ``eth_getTransactionReceipt`` to the ledger's ``/rpc``), p50 over random records of a log of
   ``--records``; the issue asks for at most 5 ms. Printed beside the bare ``eth_call`` of
   ``AnchorLog.anchorAt`` in the same run (the floor).

``bench_live``: robots (4 threads, each with its own key) POST NDJSON batches of 1,000 records
to a storage service with anchoring on: records per second against the same batches appended
in-process, and acknowledgement to verified proof, p50 and p99.

``bench_queries``: a 1-second time-window query on a template holding 1,000,000 records
(100 Hz, so a window holds 100 records), p50 over random windows through the query engine
(sealed segments' time indexes, records read from the log), against a TinyDB full scan of the
same segments for the same window. The issue asks for p50 <= 10 ms.


Ingest throughput (engineer bags) against rosbags reading and deserialising the same bag.

A bag of IMU, NavSatFix and small camera images is written with rosbags' own writer; then
each measurement runs in its own process (so its peak RSS is its own):

- ``rosbags``: AnyReader over every message, deserialize each: the baseline;
- ``ingest``: an ingest job (stage: decode, convert, validate, spool, in the service's default
  number of worker processes; commit: RecordStore.append with fsync per batch) into a fresh
  node; ratio = rosbags time / ingest time (target >= 0.25x), the staging processes' peak
  RSS (sampled, added up) printed beside the job's own,
  records per second printed beside the 120 transactions per second that chain-only storage
  reaches.


    python bench/storage.py [--records 1000000] [--queries 200] [--proof-records 200000]
        [--batches 30] [--proofs 300] [--messages 200000] [--kind ros1|sqlite3|mcap]
        [--robots 4] [--live-batches 10] [--only queries|proofs|live|ingest|bigbag]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import queue
import random
import resource
import shutil
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "clients")]

from tinydb import Query, TinyDB  # noqa: E402
from tinydb.storages import JSONStorage  # noqa: E402

from robocloud import jcs  # noqa: E402
from services.storage.catalog import Catalog  # noqa: E402
from services.storage.queries import QueryEngine, RecordQuery  # noqa: E402
from services.storage.recordlog import LogEntry, RecordLogs  # noqa: E402
from services.storage.recordstore import Authorship, RecordStore  # noqa: E402
from services.storage.segments import TABLE  # noqa: E402
from services.storage.settings import StorageSettings  # noqa: E402
from tests.procs import ServiceProcess, free_port  # noqa: E402

QUIET = {"ROBOCLOUD_LOG_LEVEL": "WARNING"}


def entries(start: int, stop: int) -> list[LogEntry]:
    return [
        LogEntry(
            jcs.canonical(
                {
                    "template": "imu@1",
                    "topic": "/imu",
                    "robot": "0x" + "ab" * 20,
                    "t": i,
                    "data": {"x": i * 0.5, "y": -i},
                }
            ),
            b'{"signer":"bench"}',
        )
        for i in range(start, stop)
    ]


def percentile(values: list[float], fraction: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(fraction * len(ordered)))]


PROOF_IMU = {"name": "imu", "fields": {"x": "float", "y": "int"}}
"""The template of ``entries``' records, which the storage service needs in its catalog to
open the logs the bench appended to."""


def bench_proofs(work: Path, records: int, batches: int, proofs: int) -> None:
    from robocloud.ledger import JsonRpcClient, LedgerService
    from robocloud.proofs import RecordId, anchor_at, verify_record_proof
    from services.storage.anchoring import NotAnchored
    from services.storage.app import _open_node
    from services.storage.identity import load_or_create

    storage_port = free_port()
    catalog = Catalog(work / "storage" / "catalog")
    version = catalog.create(PROOF_IMU, author=ROBOT)
    catalog.submit(version.id, author=ROBOT)
    catalog.review(version.id, "approve", reviewer=ROBOT)
    catalog.close()
    address = load_or_create(work / "storage", None).address
    ledger = ServiceProcess(
        "ledger",
        work / "ledger",
        {
            **QUIET,
            "ROBOCLOUD_LEDGER_GRANT_ROLES": f"storage_node:{address}",
            "ROBOCLOUD_LEDGER_POLL_INTERVAL_S": "0.2",
        },
    ).start()
    cas = ServiceProcess("cas", work / "cas", QUIET).start()
    storage_env = {
        **QUIET,
        "ROBOCLOUD_AUTH": "signed",
        "ROBOCLOUD_LEDGER_URL": ledger.url,
        "ROBOCLOUD_CAS_URL": cas.url,
        "ROBOCLOUD_STORAGE_ANCHOR_RETRY_S": "0.2",
    }
    storage = ServiceProcess("storage", work / "storage", storage_env, port=storage_port)
    try:
        settings = StorageSettings(
            service="storage",
            data_dir=work / "storage",
            ledger_url=ledger.url,
            cas_url=cas.url,
            storage_anchor_retry_s=0.2,
            storage_epoch_records=1000,
        )
        node = _open_node(settings)
        node.start()
        node.logs.append("imu@1", entries(0, records))
        node.notify(records)
        last = RecordId("imu", 1, records - 1)
        while True:
            try:
                node.proofs.record_proof(last)
                break
            except NotAnchored:
                time.sleep(0.01)
        latencies: list[float] = []
        for batch in range(batches):
            start = records + batch * 1000
            node.logs.append("imu@1", entries(start, start + 1000))
            acknowledged = time.perf_counter()
            node.notify(1000)
            newest = RecordId("imu", 1, start + 999)
            while True:
                try:
                    node.proofs.record_proof(newest)
                    break
                except NotAnchored:
                    time.sleep(0.002)
            latencies.append(time.perf_counter() - acknowledged)
        node.close()
        total = records + batches * 1000

        storage.start()
        with LedgerService(ledger.url) as service:
            anchor_log = service.contracts().anchor_log
        node_address = httpx.get(f"{storage.url}/v1/node").json()["address"]
        rng = random.Random(7)
        fetch_verify: list[float] = []
        bare_call: list[float] = []
        with httpx.Client(base_url=storage.url) as http, JsonRpcClient(f"{ledger.url}/rpc") as rpc:
            for _ in range(proofs):
                record_id = f"imu-1-{rng.randrange(total)}"
                began = time.perf_counter()
                body = http.get(f"/v1/records/{record_id}/proof").json()
                verify_record_proof(body, rpc.request, anchor_log=anchor_log, record_id=record_id)
                fetch_verify.append(time.perf_counter() - began)
                began = time.perf_counter()
                anchor_at(rpc.request, anchor_log, node_address, 1)
                bare_call.append(time.perf_counter() - began)
        p50, floor = statistics.median(fetch_verify), statistics.median(bare_call)
        print(f"log of {total:,} records, epochs of at most 2 s or 1,000 records")
        print(
            f"ack to proof: p50 {statistics.median(latencies) * 1000:.0f} ms, "
            f"p99 {percentile(latencies, 0.99) * 1000:.0f} ms over {batches} batches of 1,000 "
            f"(epoch length 2,000 ms)"
        )
        print(
            f"proof fetch + verification: p50 {p50 * 1000:.2f} ms "
            f"(target <= 5 ms: {'met' if p50 <= 0.005 else 'MISSED'}), "
            f"p99 {percentile(fetch_verify, 0.99) * 1000:.2f} ms; bare anchorAt eth_call p50 "
            f"{floor * 1000:.2f} ms; ratio {p50 / floor:.2f}x"
        )
    finally:
        storage.stop()
        cas.stop()
        ledger.stop()


ROBOT = "0x90F8bf6A479f320ead074411a4B0e7944Ea8c9C1"
PERIOD_NS = 10_000_000
SECOND_NS = 1_000_000_000
AUTHOR = Authorship(
    ROBOT,
    "storage@local",
    "POST",
    "/v1/records",
    "",
    0,
    "n" * 16,
    "0" * 64,
    "0x" + "1" * 130,
    "0" * 64,
    0,
)
IMU = {
    "name": "imu",
    "fields": {
        "seq": "int",
        "linear": {"container": {"x": "float", "y": "float", "z": "float"}},
        "angular": {"container": {"x": "float", "y": "float", "z": "float"}},
    },
}


def _record(index: int) -> dict[str, object]:
    return {
        "template": "imu@1",
        "topic": "/imu",
        "robot": ROBOT,
        "t": index * PERIOD_NS,
        "data": {
            "seq": index,
            "linear": {"x": index % 97 / 7, "y": 0.25, "z": 9.81},
            "angular": {"x": 0.01, "y": index % 13 / 3, "z": -0.5},
        },
    }


def _approved_imu(root: Path) -> Catalog:
    """A catalog under ``root`` holding ``IMU`` approved."""
    catalog = Catalog(root / "catalog")
    version = catalog.create(IMU, author=ROBOT)
    catalog.submit(version.id, author=ROBOT)
    catalog.review(version.id, "approve", reviewer=ROBOT)
    return catalog


def _fill(root: Path, count: int) -> RecordStore:
    store = RecordStore(root, RecordLogs(root / "logs"), _approved_imu(root))
    started = time.perf_counter()
    batch = 10_000
    for first in range(0, count, batch):
        store.append([_record(i) for i in range(first, min(count, first + batch))], author=AUTHOR)
    seconds = time.perf_counter() - started
    print(f"  filled {count} records in {seconds:.1f} s ({count / seconds:,.0f} records/s)")
    return store


def _live_record(robot: str, index: int) -> dict[str, object]:
    return {**_record(index), "robot": robot}


PROOF_WAIT_S = 60
"""How long after its acknowledgement a batch's proof may take before the bench gives up."""


def bench_live(work: Path, robots: int, batches: int) -> None:
    """Live robots: ``robots`` threads, each with its own key, POST NDJSON batches of 1,000
    records to a storage service (signed requests, anchoring on), back to back. Printed:
    records per second, against the same batches appended in-process through
    ``RecordStore.append`` (no HTTP, no signature) in the same run, and the time from each
    batch's acknowledgement to the moment its last record's proof verifies against the chain
    (a prover thread fetches and verifies while the robots write), p50 and p99. One record
    is proved first, so that the node's role is granted and its anchorer running before the
    clock starts."""
    from robocloud.identity import Identity
    from robocloud.ledger import JsonRpcClient, LedgerService
    from robocloud.proofs import verify_record_proof
    from robocloud.storage import Storage
    from services.storage.identity import load_or_create

    keys = [Identity.generate() for _ in range(robots)]
    payloads = [
        [
            [_live_record(key.address, batch * 1000 + i) for i in range(1000)]
            for batch in range(batches)
        ]
        for key in keys
    ]
    total = robots * batches * 1000
    store = RecordStore(
        work / "direct", RecordLogs(work / "direct" / "logs"), _approved_imu(work / "direct")
    )
    started = time.perf_counter()
    for robot_batches in payloads:
        for batch in robot_batches:
            store.append(batch, author=AUTHOR)
    direct = total / (time.perf_counter() - started)
    store.close()

    _approved_imu(work / "storage").close()
    address = load_or_create(work / "storage", None).address
    ledger = ServiceProcess(
        "ledger",
        work / "ledger",
        {**QUIET, "ROBOCLOUD_LEDGER_GRANT_ROLES": f"storage_node:{address}"},
    ).start()
    cas = ServiceProcess("cas", work / "cas", QUIET).start()
    storage = ServiceProcess(
        "storage",
        work / "storage",
        {
            **QUIET,
            "ROBOCLOUD_AUTH": "signed",
            "ROBOCLOUD_LEDGER_URL": ledger.url,
            "ROBOCLOUD_CAS_URL": cas.url,
            "ROBOCLOUD_STORAGE_ANCHOR_RETRY_S": "0.2",
        },
    ).start()
    try:
        with LedgerService(ledger.url) as service:
            anchor_log = service.contracts().anchor_log
        acknowledged: queue.Queue[tuple[float, str] | None] = queue.Queue()
        latencies: list[float] = []
        unproved: list[str] = []

        def robot(key: Identity, batches_of: list[list[dict[str, object]]]) -> None:
            with Storage(storage.url, key, timeout=120) as client:
                for batch in batches_of:
                    ids = client.append(batch)
                    acknowledged.put((time.perf_counter(), ids[-1]))

        def prover() -> None:
            with (
                httpx.Client(base_url=storage.url) as http,
                JsonRpcClient(f"{ledger.url}/rpc") as rpc,
            ):
                while (item := acknowledged.get()) is not None:
                    acked, record_id = item
                    while (answer := http.get(f"/v1/records/{record_id}/proof")).status_code != 200:
                        if time.perf_counter() - acked > PROOF_WAIT_S:
                            unproved.append(f"{record_id}: {answer.text[:300]}")
                            return
                        time.sleep(0.005)
                    verify_record_proof(
                        answer.json(), rpc.request, anchor_log=anchor_log, record_id=record_id
                    )
                    latencies.append(time.perf_counter() - acked)

        with Storage(storage.url, keys[0]) as client:
            warmup = client.append([_live_record(keys[0].address, 10**7)])[0]
        acknowledged.put((time.perf_counter(), warmup))
        acknowledged.put(None)
        prover()
        latencies.clear()
        if unproved:
            raise SystemExit(f"no proof within {PROOF_WAIT_S} s: {unproved[0]}")
        proving = threading.Thread(target=prover)
        proving.start()
        writers = [
            threading.Thread(target=robot, args=pair) for pair in zip(keys, payloads, strict=True)
        ]
        started = time.perf_counter()
        for writer in writers:
            writer.start()
        for writer in writers:
            writer.join()
        rate = total / (time.perf_counter() - started)
        acknowledged.put(None)
        proving.join()
        if unproved:
            raise SystemExit(f"no proof within {PROOF_WAIT_S} s: {unproved[0]}")
    finally:
        storage.stop()
        cas.stop()
        ledger.stop()
    print(f"== live records: {robots} robots, {batches} NDJSON batches of 1,000 each, anchoring on")
    print(
        f"  {rate:,.0f} records/s over HTTP ({rate / 120:,.0f}x the 120 tx/s of chain-only "
        f"storage); in-process RecordStore.append {direct:,.0f} records/s: "
        f"ratio {rate / direct:.2f}x"
    )
    print(
        f"  acknowledgement to verified proof: p50 {statistics.median(latencies) * 1000:.0f} ms, "
        f"p99 {percentile(latencies, 0.99) * 1000:.0f} ms (epochs of at most 2,000 ms)"
    )


def _full_scan(store: RecordStore, start: int, end: int) -> int:
    """The baseline: every sealed segment opened with TinyDB and searched, as TinyDB alone would."""
    views = store.views("imu@1")
    assert views is not None
    found = 0
    for segment in views.sealed:
        database = TinyDB(
            views.directory / f"{segment.name}.json", storage=JSONStorage, access_mode="r"
        )
        found += len(database.table(TABLE).search((Query()._t >= start) & (Query()._t < end)))
        database.close()
    return found + sum(1 for doc in views.tail if start <= doc["_t"] < end)


def bench_queries(records: int = 1_000_000, queries: int = 200) -> None:
    print(f"== time-window queries over {records:,} records")
    with tempfile.TemporaryDirectory(prefix="bench-storage-") as directory:
        store = _fill(Path(directory), records)
        engine = QueryEngine(store)
        span = records * PERIOD_NS
        rng = random.Random(7)
        timings = []
        for _ in range(queries):
            start = rng.randrange(0, span - SECOND_NS)
            began = time.perf_counter()
            page = engine.records(
                RecordQuery(template="imu@1", start=start, end=start + SECOND_NS, limit=1000)
            )
            timings.append(time.perf_counter() - began)
            assert len(page.records) == SECOND_NS // PERIOD_NS, len(page.records)
        p50 = statistics.median(timings)
        p99 = statistics.quantiles(timings, n=100)[98]
        start = rng.randrange(0, span - SECOND_NS)
        began = time.perf_counter()
        matched = _full_scan(store, start, start + SECOND_NS)
        scan = time.perf_counter() - began
        assert matched == SECOND_NS // PERIOD_NS
        print(
            f"  1 s window (100 records): p50 {p50 * 1000:.2f} ms, p99 {p99 * 1000:.2f} ms "
            f"(target p50 <= 10 ms)"
        )
        print(
            f"  TinyDB full scan of the same template: {scan * 1000:.0f} ms; "
            f"indexed query {scan / p50:,.0f}x faster at p50"
        )
        store.close()
        store.logs.close()
        store.catalog.close()


CHAIN_TPS = 120
START_NS = 1_700_000_000_000_000_000
"""November 2023 in nanoseconds since the epoch, as real recordings stamp their messages."""


@dataclass(frozen=True)
class Result:
    name: str
    seconds: float
    messages: int
    peak_rss_mib: float
    staging_rss_mib: float = 0.0
    """Peak of the staging processes' resident sets, added up (they run beside the process)."""

    def staging_memory(self) -> str:
        if not self.staging_rss_mib:
            return ""
        return f" (+ {self.staging_rss_mib:.0f} MiB in staging processes)"


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _children(pid: int) -> list[int]:
    """The processes ``pid``'s threads started (Linux ``/proc/PID/task/TID/children``)."""
    found: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        found += [int(child) for child in (task / "children").read_text().split()]
    return found


def _rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


class StagingMemory:
    """Samples, every 50 ms, the resident sets of the forkserver this process started and of
    the staging processes it forked, added up; ``peak_mib`` is the highest sum seen."""

    def __init__(self) -> None:
        self.peak_mib = 0.0
        self._servers: dict[int, bool] = {}
        """Child pid: whether it is a forkserver (its command line is read once)."""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)

    def __enter__(self) -> StagingMemory:
        self._thread.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self._stop.set()
        self._thread.join()

    def _sample(self) -> None:
        while not self._stop.wait(0.05):
            try:
                self.peak_mib = max(self.peak_mib, self._now())
            except (FileNotFoundError, ProcessLookupError):
                continue

    def _is_server(self, pid: int) -> bool:
        if pid not in self._servers:
            command = Path(f"/proc/{pid}/cmdline").read_bytes()
            self._servers[pid] = b"multiprocessing.forkserver" in command
        return self._servers[pid]

    def _now(self) -> float:
        servers = [pid for pid in _children(os.getpid()) if self._is_server(pid)]
        workers = [child for server in servers for child in _children(server)]
        return sum(_rss_mib(pid) for pid in [*servers, *workers])


def bench_rosbags(bag: Path, work: Path) -> Result:
    from rosbags.highlevel import AnyReader

    started = time.perf_counter()
    count = 0
    with AnyReader([bag]) as reader:
        for connection, _, raw in reader.messages():
            reader.deserialize(raw, connection.msgtype)
            count += 1
    return Result("rosbags read+deserialize", time.perf_counter() - started, count, _peak_rss_mib())


def _ingest(
    bag: Path,
    work: Path,
    logs: Any,
    notify: Callable[[int], None] | None,
    add_blobs: Callable[[Sequence[bytes]], list[str]] | None = None,
) -> tuple[int, float]:
    """One ingest job of ``bag`` into a fresh record store over ``logs``: its records, and
    the seconds from the job's submission to its end.

    The node is opened first, as a running service has it: templates approved and bound, the
    server its staging processes fork from loaded. Image bytes go through ``add_blobs`` (a cas
    client's ``add_blobs``), or are only hashed into their CID when it is None."""
    from robocloud.identity import Identity
    from robocloud.unixfs import import_bytes
    from services.storage.catalog import Catalog
    from services.storage.ingest import IngestJobs
    from services.storage.matcher import Bindings, draft_template
    from services.storage.recordstore import Authorship, RecordStore, collect_garbage_less_often
    from services.storage.staging import CasBlobs, start_workers_server
    from tests.bagfactory import TOPICS, typestore_for

    collect_garbage_less_often()
    root = work / "node"
    catalog = Catalog(root / "catalog")
    store = RecordStore(root, logs, catalog, notify=notify)
    bindings = Bindings(root / "bindings.json")
    author = Identity.generate().address
    for msgtype in TOPICS.values():
        version = catalog.create(draft_template(typestore_for("ros1"), msgtype), author=author)
        catalog.submit(version.id, author=author)
        catalog.review(version.id, "approve", reviewer=author)
        bindings.bind(template_id=version.id, msgtype=msgtype)
    blobs = CasBlobs(add_blobs or (lambda new: [str(import_bytes(data)[1]) for data in new]))
    workers = StorageSettings.model_fields["storage_ingest_workers"].get_default(
        call_default_factory=True
    )
    jobs = IngestJobs(
        root / "jobs", store, logs, bindings, lambda: blobs.put_many, staging_workers=workers
    )
    signer = Authorship(
        signer=author,
        audience="storage@local",
        method="POST",
        path="/v1/ingest",
        query="",
        timestamp=int(time.time()),
        nonce="bench-nonce-000000",
        content_sha256="0" * 64,
        signature="0x" + "0" * 130,
        request_sha256="0" * 64,
        received_at_ns=time.time_ns(),
    )
    copy = work / bag.name
    if bag.is_dir():
        shutil.copytree(bag, copy)
    else:
        shutil.copyfile(bag, copy)
    start_workers_server(wait=True)
    started = time.perf_counter()
    job = jobs.wait(jobs.submit(copy, "upload:bench", signer).id, timeout_s=3600)
    seconds = time.perf_counter() - started
    if job.status != "succeeded":
        raise SystemExit(f"ingest failed: {job.error}")
    jobs.close()
    store.close()
    return job.records_committed, seconds


def bench_ingest(bag: Path, work: Path) -> Result:
    from services.storage.recordlog import RecordLogs

    logs = RecordLogs(work / "logs")
    with StagingMemory() as staging:
        count, seconds = _ingest(bag, work, logs, None)
    logs.close()
    return Result("ingest, anchoring off", seconds, count, _peak_rss_mib(), staging.peak_mib)


def bench_ingest_anchored(bag: Path, work: Path) -> Result:
    """The same ingest into a storage node that cuts epochs and anchors them on a ledger
    started here (the node's role granted by the ledger at its start)."""
    from services.storage.app import _open_node
    from services.storage.identity import load_or_create

    address = load_or_create(work / "storage", None).address
    grants = {"ROBOCLOUD_LEDGER_GRANT_ROLES": f"storage_node:{address}"}
    ledger = ServiceProcess("ledger", work / "ledger", {**QUIET, **grants}).start()
    cas = ServiceProcess("cas", work / "cas", QUIET).start()
    try:
        settings = StorageSettings(
            service="storage", data_dir=work / "storage", ledger_url=ledger.url, cas_url=cas.url
        )
        node = _open_node(settings)
        node.start()
        with StagingMemory() as staging:
            count, seconds = _ingest(bag, work, node.logs, node.notify)
        deadline = time.monotonic() + 60
        while node.epochs.last_anchored() < node.epochs.last() and time.monotonic() < deadline:
            time.sleep(0.2)
        anchored = f"{node.epochs.last_anchored()}/{node.epochs.last()} epochs anchored"
        node.close()
    finally:
        cas.stop()
        ledger.stop()
    return Result(
        f"ingest, anchoring on ({anchored})", seconds, count, _peak_rss_mib(), staging.peak_mib
    )


MEASUREMENTS: list[Callable[[Path, Path], Result]] = [
    bench_rosbags,
    bench_ingest,
    bench_ingest_anchored,
]


def _run(measure: Callable[[Path, Path], Result], bag: Path, out: multiprocessing.Queue) -> None:
    with tempfile.TemporaryDirectory() as work:
        out.put(measure(bag, Path(work)))


def isolated(measure: Callable[[Path, Path], Result], bag: Path) -> Result:
    context = multiprocessing.get_context("spawn")
    results: multiprocessing.Queue = context.Queue()
    process = context.Process(target=_run, args=(measure, bag, results))
    process.start()
    result: Result = results.get()
    process.join()
    return result


def bench_ingestion(options: argparse.Namespace) -> None:
    from tests.bagfactory import write_bag

    with tempfile.TemporaryDirectory() as scratch:
        name = "bench.bag" if options.kind == "ros1" else "bench"
        started = time.perf_counter()
        bag = write_bag(Path(scratch) / name, options.kind, options.messages, start_ns=START_NS)
        size = sum(p.stat().st_size for p in ([bag] if bag.is_file() else bag.iterdir()))
        print(
            f"bag: {options.messages} messages ({options.kind}, {size / 2**20:.1f} MiB), "
            f"written in {time.perf_counter() - started:.1f} s"
        )
        results = [isolated(measure, bag) for measure in MEASUREMENTS]
    baseline = results[0]
    for result in results:
        rate = result.messages / result.seconds
        print(
            f"{result.name:48} {result.seconds:8.2f} s  {rate:10.0f} msg/s  "
            f"{baseline.seconds / result.seconds:5.2f}x rosbags  "
            f"peak RSS {result.peak_rss_mib:6.0f} MiB{result.staging_memory()}"
        )
    off, on = results[1], results[2]
    rate = on.messages / on.seconds
    print(
        f"ingest, anchored: {rate:.0f} records/s = {rate / CHAIN_TPS:.0f}x the {CHAIN_TPS} tx/s "
        f"of chain-only storage; {baseline.seconds / on.seconds:.2f}x rosbags (target >= 0.25x); "
        f"{off.seconds / on.seconds:.2f}x the same ingest with anchoring off (target >= 0.9x)"
    )


# ----- a bag of about 1 GB: memory bounded whatever the bag's size (issue 15) -----


def _vm_hwm_mib(pid: int) -> float:
    """A child's peak resident set (Linux ``VmHWM``)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def bench_bigbag_ingest(bag: Path, work: Path) -> Result:
    """An ingest job into a fresh record store, image bytes stored in a cas started here."""
    from robocloud.cas import Cas
    from robocloud.identity import Identity
    from services.storage.recordlog import RecordLogs

    cas = ServiceProcess("cas", work / "cas", QUIET).start()
    try:
        logs = RecordLogs(work / "logs")
        with Cas(cas.url, Identity.generate()) as client, StagingMemory() as staging:
            count, seconds = _ingest(
                bag, work, logs, None, lambda new: [str(cid) for cid in client.add_blobs(new)]
            )
        logs.close()
        assert cas.process is not None
        cas_rss = _vm_hwm_mib(cas.process.pid)
    finally:
        cas.stop()
    return Result(
        f"ingest, images to cas (cas peak RSS {cas_rss:.0f} MiB)",
        seconds,
        count,
        _peak_rss_mib(),
        staging.peak_mib,
    )


def bench_bigbag(options: argparse.Namespace) -> None:
    from tests.bagfactory import (
        CAMERA_HZ,
        FRAME_BYTES,
        IMU_HZ,
        camera_run,
        typestore_for,
        write_messages,
    )

    for gigabytes in options.bag_gb:
        with tempfile.TemporaryDirectory(prefix="bench-bigbag-") as scratch:
            name = "big.bag" if options.kind == "ros1" else "big"
            started = time.perf_counter()
            store = typestore_for(options.kind)
            frames = max(1, round(gigabytes * 1e9 / FRAME_BYTES))
            bag = write_messages(
                Path(scratch) / name, options.kind, store, camera_run(store, frames)
            )
            size = sum(p.stat().st_size for p in ([bag] if bag.is_file() else bag.iterdir()))
            print(
                f"== bag of {size / 1e9:.2f} GB ({options.kind}; 640x480 rgb8 at {CAMERA_HZ} Hz, "
                f"IMU at {IMU_HZ} Hz, NavSatFix at {CAMERA_HZ} Hz), written in "
                f"{time.perf_counter() - started:.0f} s"
            )
            results = [isolated(bench_rosbags, bag), isolated(bench_bigbag_ingest, bag)]
        for result in results:
            rate = size / 1e6 / result.seconds
            print(
                f"  {result.name:54} {result.seconds:7.1f} s  {rate:6.1f} MB/s"
                f"  {result.messages:7} msg  peak RSS {result.peak_rss_mib:5.0f} MiB"
                f"{result.staging_memory()}"
            )
        print(f"  ingest / rosbags time: {results[1].seconds / results[0].seconds:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--records", type=int, default=1_000_000)
    parser.add_argument("--queries", type=int, default=200)
    parser.add_argument("--proof-records", type=int, default=200_000)
    parser.add_argument("--batches", type=int, default=30)
    parser.add_argument("--proofs", type=int, default=300)
    parser.add_argument("--messages", type=int, default=200_000)
    parser.add_argument("--kind", choices=["ros1", "sqlite3", "mcap"], default="ros1")
    parser.add_argument("--robots", type=int, default=4)
    parser.add_argument("--live-batches", type=int, default=10, help="batches of 1,000 per robot")
    parser.add_argument("--only", choices=["queries", "proofs", "live", "ingest", "bigbag"])
    parser.add_argument(
        "--bag-gb",
        type=float,
        nargs="+",
        default=[1.0],
        help="bigbag: the sizes of bag to ingest (several show how memory follows the size)",
    )
    args = parser.parse_args()
    if args.only == "bigbag":
        bench_bigbag(args)
        return
    if args.only in (None, "ingest"):
        bench_ingestion(args)
    if args.only in (None, "queries"):
        bench_queries(args.records, args.queries)
    if args.only in (None, "proofs"):
        with tempfile.TemporaryDirectory() as work:
            bench_proofs(Path(work), args.proof_records, args.batches, args.proofs)
    if args.only in (None, "live"):
        with tempfile.TemporaryDirectory() as work:
            bench_live(Path(work), args.robots, args.live_batches)


if __name__ == "__main__":
    main()
