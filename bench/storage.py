"""Storage ingest throughput against rosbags reading and deserialising the same bag.

A bag of IMU, NavSatFix and small camera images is written with rosbags' own writer; then
each measurement runs in its own process (so its peak RSS is its own):

- ``rosbags``: AnyReader over every message, deserialize each: the baseline;
- ``ingest``: an ingest job (stage: decode, convert, validate, spool; commit: RecordStore.append
  with fsync per batch) into a fresh node; ratio = rosbags time / ingest time (target >= 0.25x),
  records per second printed beside the 120 transactions per second that chain-only storage
  reaches.

Each measurement is a function returning a ``Result``; add yours to ``MEASUREMENTS``
(``bench_queries``, proof latency, anchoring on/off once the anchorer is wired).

    python bench/storage.py [--messages 200000] [--kind ros1|sqlite3|mcap]
"""

from __future__ import annotations

import argparse
import multiprocessing
import resource
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "clients")]

from robocloud.identity import Identity  # noqa: E402

CHAIN_TPS = 120
START_NS = 1_000_000_000_000
"""Inside 2**53: the records' JCS form cannot hold epoch nanoseconds in ``t`` yet."""


@dataclass(frozen=True)
class Result:
    name: str
    seconds: float
    messages: int
    peak_rss_mib: float


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def bench_rosbags(bag: Path, work: Path) -> Result:
    from rosbags.highlevel import AnyReader

    started = time.perf_counter()
    count = 0
    with AnyReader([bag]) as reader:
        for connection, _, raw in reader.messages():
            reader.deserialize(raw, connection.msgtype)
            count += 1
    return Result("rosbags read+deserialize", time.perf_counter() - started, count, _peak_rss_mib())


def bench_ingest(bag: Path, work: Path) -> Result:
    from robocloud.unixfs import import_bytes
    from services.storage.catalog import Catalog
    from services.storage.ingest import CasBlobs, IngestJobs
    from services.storage.matcher import Bindings, draft_template
    from services.storage.recordlog import RecordLogs
    from services.storage.recordstore import Authorship, RecordStore
    from tests.bagfactory import TOPICS, typestore_for

    root = work / "node"
    catalog = Catalog(root / "catalog")
    logs = RecordLogs(root / "logs")
    store = RecordStore(root, logs, catalog)
    bindings = Bindings(root / "bindings.json")
    author = Identity.generate().address
    for msgtype in TOPICS.values():
        version = catalog.create(draft_template(typestore_for("ros1"), msgtype), author=author)
        catalog.submit(version.id, author=author)
        catalog.review(version.id, "approve", reviewer=author)
        bindings.bind(template_id=version.id, msgtype=msgtype)
    blobs = CasBlobs(lambda data: str(import_bytes(data)[1]))
    jobs = IngestJobs(root / "jobs", store, logs, bindings, lambda: blobs)
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
    copy.write_bytes(bag.read_bytes())
    started = time.perf_counter()
    job = jobs.wait(jobs.submit(copy, "upload:bench", signer).id, timeout_s=3600)
    seconds = time.perf_counter() - started
    if job.status != "succeeded":
        raise SystemExit(f"ingest failed: {job.error}")
    jobs.close()
    store.close()
    return Result("ingest (stage + commit)", seconds, job.records_committed, _peak_rss_mib())


MEASUREMENTS: list[Callable[[Path, Path], Result]] = [bench_rosbags, bench_ingest]


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


def main() -> None:
    from tests.bagfactory import write_bag

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--messages", type=int, default=200_000)
    parser.add_argument("--kind", choices=["ros1", "sqlite3", "mcap"], default="ros1")
    options = parser.parse_args()
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
            f"{result.name:28} {result.seconds:8.2f} s  {rate:10.0f} msg/s  "
            f"{baseline.seconds / result.seconds:5.2f}x rosbags  "
            f"peak RSS {result.peak_rss_mib:6.0f} MiB"
        )
    ingest = results[1]
    print(
        f"ingest: {ingest.messages / ingest.seconds:.0f} records/s = "
        f"{ingest.messages / ingest.seconds / CHAIN_TPS:.0f}x the {CHAIN_TPS} tx/s of chain-only "
        f"storage; ratio to rosbags {baseline.seconds / ingest.seconds:.2f}x (target >= 0.25x)"
    )


if __name__ == "__main__":
    main()
