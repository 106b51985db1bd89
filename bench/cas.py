"""cas throughput and memory: add and cat over HTTP against ``sha256sum`` on the same file.

Prints ratios (sha256sum's time over ours: 1.0x means as fast as hashing the file once);
the issue asks for add >= 0.5x and cat >= 1.0x. Also prints the gateway's peak RSS while it
adds a larger file (the issue: under 300 MB for 1 GiB), ``put DIR`` and ``get DIR`` of many
small files: files per second and the ratio to the same bytes as one file,
``dag/import`` of a CAR of new content, its root pinned and not (``pin-roots=false`` walks no
DAG), and ``robocloud get`` of a small file, start included.

    python bench/cas.py [--size-mib 256] [--rss-mib 1024] [--rounds 3] [--dir-files 10000]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import httpx

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "clients")]

from robocloud.car import write_car  # noqa: E402
from robocloud.cas import Cas  # noqa: E402
from robocloud.client import ServiceClient  # noqa: E402
from robocloud.identity import Identity  # noqa: E402
from robocloud.unixfs import import_bytes  # noqa: E402
from tests.integration.services.cas.conftest import multipart  # noqa: E402
from tests.procs import ServiceProcess  # noqa: E402

MIB = 1024 * 1024
T = TypeVar("T")


def random_file(path: Path, size: int) -> Path:
    with path.open("wb") as out:
        for _ in range(size // MIB):
            out.write(os.urandom(MIB))
        out.write(os.urandom(size % MIB))
    return path


def best_of(rounds: int, action: Callable[[], object]) -> float:
    times = []
    for _ in range(rounds):
        started = time.perf_counter()
        action()
        times.append(time.perf_counter() - started)
    return min(times)


def best_of_prepared(rounds: int, prepare: Callable[[], T], action: Callable[[T], object]) -> float:
    """``best_of`` for an action whose input is made anew each round, outside the time."""
    times = []
    for _ in range(rounds):
        prepared = prepare()
        started = time.perf_counter()
        action(prepared)
        times.append(time.perf_counter() - started)
    return min(times)


def sha256sum(path: Path) -> None:
    subprocess.run(["sha256sum", str(path)], check=True, capture_output=True)


def stream_to_nowhere(method: str, url: str, **params: object) -> int:
    received = 0
    with httpx.stream(method, url, params=params, timeout=120) as response:
        response.raise_for_status()
        for chunk in response.iter_raw(MIB):
            received += len(chunk)
    return received


def peak_rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmHWM in /proc status")


def report(name: str, seconds: float, size: int, baseline: float) -> None:
    rate = size / seconds / MIB
    print(f"{name:<34} {seconds:7.3f} s {rate:8.1f} MiB/s   {baseline / seconds:5.2f}x sha256sum")


def small_files(root: Path, count: int, size: int) -> Path:
    root.mkdir()
    for n in range(count):
        (root / f"file-{n:05d}.bin").write_bytes(os.urandom(size))
    return root


def bench_directory(cas: Cas, work: Path, count: int, rounds: int) -> None:
    """``put DIR`` of ``count`` 4 KiB files against one file of the same bytes, new content
    each round (content already stored would cost the gateway nothing); then ``get DIR`` of
    such a tree against ``get`` of that file."""
    trees = [small_files(work / f"tree-{n}", count, 4096) for n in range(rounds)]
    directories = iter(trees)
    as_directory = best_of(rounds, lambda: cas.add_directory(next(directories)))
    singles = iter([random_file(work / f"same-{n}.bin", count * 4096) for n in range(rounds)])
    as_file = best_of(rounds, lambda: cas.add_file(next(singles)))
    print(
        f"put DIR of {count} x 4 KiB files       {as_directory:7.3f} s "
        f"{count / as_directory:8.0f} files/s   {as_file / as_directory:5.2f}x "
        f"one file of the same bytes ({as_file:.3f} s)"
    )
    directory, single = cas.add_directory(trees[0]), cas.add_file(work / "same-0.bin")
    targets = iter([work / f"got-{n}" for n in range(rounds)])
    got_directory = best_of(rounds, lambda: cas.get_tree(directory, next(targets)))
    got_file = best_of(rounds, lambda: cas.get_to_file(single, work / "got.bin"))
    print(
        f"get DIR of {count} x 4 KiB files       {got_directory:7.3f} s "
        f"{count / got_directory:8.0f} files/s   {got_file / got_directory:5.2f}x "
        f"one file of the same bytes ({got_file:.3f} s)"
    )


def bench_cli_get(cas: Cas, work: Path, rounds: int) -> None:
    """``robocloud get`` of a 4 KiB file, run as a robot's script runs it: a fresh process
    each time, so the command's start (its imports) counts; against an empty interpreter's
    start and the SDK's get of the same file in this process."""
    cid = cas.add_bytes(os.urandom(4096))
    command = [str(Path(sys.executable).with_name("robocloud")), "get", str(cid), "--force"]
    command += ["-o", str(work / "cli-got.bin"), "--cas", cas.base_url]
    cli = best_of(rounds, lambda: subprocess.run(command, check=True, capture_output=True))
    empty = best_of(rounds, lambda: subprocess.run([sys.executable, "-c", "pass"], check=True))
    in_process = best_of(rounds, lambda: cas.get_to_file(cid, work / "sdk-got.bin"))
    print(
        f"CLI get of a 4 KiB file              {cli:7.3f} s   {cli / empty:5.1f}x an empty "
        f"python start ({empty:.3f} s); the SDK's get in process {in_process:.4f} s"
    )


def new_car_body(size: int) -> tuple[bytes, str]:
    """A ``dag/import`` body: one CAR of ``size`` new random bytes as kubo chunks them."""
    blocks, root = import_bytes(os.urandom(size))
    return multipart(("data.car", b"".join(write_car([root], blocks))))


def bench_import(url: str, size: int, rounds: int, baseline: float) -> None:
    """``dag/import`` of a CAR of new content each round, its root pinned (the DAG walked
    to check it is whole) and not (nothing walked, as kubo)."""
    with ServiceClient(url, Identity.generate(), timeout=600) as signed:
        for pin_roots in ("true", "false"):

            def post(body: tuple[bytes, str], pin_roots: str = pin_roots) -> None:
                content, content_type = body
                signed.request(
                    "POST",
                    "/api/v0/dag/import",
                    params={"pin-roots": pin_roots},
                    content=content,
                    headers={"Content-Type": content_type},
                )

            seconds = best_of_prepared(rounds, lambda: new_car_body(size), post)
            report(f"dag/import, pin-roots={pin_roots}", seconds, size, baseline)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size-mib", type=int, default=256)
    parser.add_argument("--rss-mib", type=int, default=1024)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--dir-files", type=int, default=10_000)
    args = parser.parse_args()
    size = args.size_mib * MIB
    with tempfile.TemporaryDirectory(prefix="bench-cas-") as scratch:
        work = Path(scratch)
        data = random_file(work / "data.bin", size)
        service = ServiceProcess("cas", work / "cas", {"ROBOCLOUD_LOG_LEVEL": "WARNING"})
        with service, Cas(service.url, Identity.generate(), timeout=600) as cas:
            baseline = best_of(args.rounds, lambda: sha256sum(data))
            print(f"file: {args.size_mib} MiB, best of {args.rounds} rounds")
            report("sha256sum (baseline)", baseline, size, baseline)
            fresh_files = iter(
                [random_file(work / f"add-{n}.bin", size) for n in range(args.rounds)]
            )
            add = best_of(args.rounds, lambda: cas.add_file(next(fresh_files)))
            report("add (SDK add_file, new content)", add, size, baseline)
            cid = cas.add_file(data)
            cat = best_of(
                args.rounds,
                lambda: stream_to_nowhere("POST", f"{service.url}/api/v0/cat", arg=str(cid)),
            )
            report("cat (kubo RPC)", cat, size, baseline)
            gateway = best_of(
                args.rounds, lambda: stream_to_nowhere("GET", f"{service.url}/ipfs/{cid}")
            )
            report("gateway GET /ipfs/{cid}", gateway, size, baseline)
            verified = best_of(args.rounds, lambda: cas.get_to_file(cid, work / "out.bin"))
            report("get (SDK, CAR verified locally)", verified, size, baseline)
            assert service.process is not None
            rss = peak_rss_mib(service.process.pid)
            print(f"gateway peak RSS after the runs above: {rss:.0f} MiB")
            bench_import(service.url, size, args.rounds, baseline)
            bench_directory(cas, work, args.dir_files, args.rounds)
            bench_cli_get(cas, work, args.rounds)
        large = random_file(work / "large.bin", args.rss_mib * MIB)
        data.unlink()
        fresh = ServiceProcess("cas", work / "cas-rss", {"ROBOCLOUD_LOG_LEVEL": "WARNING"})
        with fresh, Cas(fresh.url, Identity.generate(), timeout=600) as cas:
            started = time.perf_counter()
            cas.add_file(large)
            seconds = time.perf_counter() - started
            assert fresh.process is not None
            rss = peak_rss_mib(fresh.process.pid)
            print(
                f"add {args.rss_mib} MiB: {seconds:.2f} s, gateway peak RSS {rss:.0f} MiB "
                f"(limit 300 MiB)"
            )


if __name__ == "__main__":
    main()
