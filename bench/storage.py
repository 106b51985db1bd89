"""Storage benchmarks, each printing ratios against a baseline measured in the same run.

``bench_queries``: a 1-second time-window query on a template holding 1,000,000 records
(100 Hz, so a window holds 100 records), p50 over random windows through the query engine
(sealed segments' time indexes, records read from the log), against a TinyDB full scan of the
same segments for the same window. The issue asks for p50 <= 10 ms.

    python bench/storage.py [--records 1000000] [--queries 200]
"""

from __future__ import annotations

import argparse
import random
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "clients")]

from tinydb import Query, TinyDB  # noqa: E402
from tinydb.storages import JSONStorage  # noqa: E402

from services.storage.catalog import Catalog  # noqa: E402
from services.storage.queries import QueryEngine, RecordQuery  # noqa: E402
from services.storage.recordlog import RecordLogs  # noqa: E402
from services.storage.recordstore import Authorship, RecordStore  # noqa: E402
from services.storage.segments import TABLE  # noqa: E402

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


def _fill(root: Path, count: int) -> RecordStore:
    catalog = Catalog(root / "catalog")
    version = catalog.create(IMU, author=ROBOT)
    catalog.submit(version.id, author=ROBOT)
    catalog.review(version.id, "approve", reviewer=ROBOT)
    store = RecordStore(root, RecordLogs(root / "logs"), catalog)
    started = time.perf_counter()
    batch = 10_000
    for first in range(0, count, batch):
        store.append([_record(i) for i in range(first, min(count, first + batch))], author=AUTHOR)
    seconds = time.perf_counter() - started
    print(f"  filled {count} records in {seconds:.1f} s ({count / seconds:,.0f} records/s)")
    return store


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--records", type=int, default=1_000_000)
    parser.add_argument("--queries", type=int, default=200)
    options = parser.parse_args()
    bench_queries(options.records, options.queries)


if __name__ == "__main__":
    main()
