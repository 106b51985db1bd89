"""The chain's lock goes to its waiters in arrival order, even against a thread that lets
go and asks again at once (which Python's own locks let win)."""

from __future__ import annotations

import signal
import threading
import time

import pytest

from services.common.fairlock import FairLock


def queued(lock: FairLock, count: int) -> None:
    """Wait until ``count`` threads wait for ``lock``."""
    deadline = time.monotonic() + 5
    while len(lock._waiters) < count:
        assert time.monotonic() < deadline, "the waiters never queued"
        time.sleep(0.001)


def test_a_thread_asking_again_at_once_goes_behind_the_waiters() -> None:
    lock, order = FairLock(), []

    def waiter(name: str) -> None:
        with lock:
            order.append(name)

    lock.acquire()
    threads = []
    for count, name in enumerate(("first", "second", "third"), start=1):
        threads.append(threading.Thread(target=waiter, args=(name,)))
        threads[-1].start()
        queued(lock, count)
    lock.release()
    with lock:
        order.append("again")
    for thread in threads:
        thread.join()
    assert order == ["first", "second", "third", "again"]


def test_the_holder_takes_it_again_without_waiting() -> None:
    lock, got = FairLock(), threading.Event()

    def other() -> None:
        with lock:
            got.set()

    with lock:
        with lock:
            thread = threading.Thread(target=other)
            thread.start()
            queued(lock, 1)
        assert not got.is_set(), "an inner release let the lock go"
    thread.join(5)
    assert got.is_set()


def test_only_the_holder_releases() -> None:
    lock = FairLock()
    with pytest.raises(RuntimeError, match="does not hold"):
        lock.release()
    with lock:
        failures = []

        def stranger() -> None:
            try:
                lock.release()
            except RuntimeError as exc:
                failures.append(str(exc))

        thread = threading.Thread(target=stranger)
        thread.start()
        thread.join()
    assert failures == ["cannot release a FairLock this thread does not hold"]
    with lock:
        pass


def test_an_interrupted_wait_leaves_the_queue() -> None:
    """A waiter interrupted by a signal must not be handed the lock later: it would hold it
    forever, and every other thread would wait behind it."""
    lock, holding, release = FairLock(), threading.Event(), threading.Event()

    def holder() -> None:
        with lock:
            holding.set()
            release.wait(5)

    def interrupt(signum: int, frame: object) -> None:
        raise TimeoutError("interrupted")

    thread = threading.Thread(target=holder)
    thread.start()
    holding.wait(5)
    previous = signal.signal(signal.SIGALRM, interrupt)
    try:
        signal.setitimer(signal.ITIMER_REAL, 0.2)
        with pytest.raises(TimeoutError, match="interrupted"):
            lock.acquire()
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    assert len(lock._waiters) == 0
    release.set()
    thread.join(5)
    with lock:
        pass
