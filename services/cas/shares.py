"""What one robot may take of the store: bytes kept pinned, and new bytes written an hour.

The bound on pins (``PinSet``) alone left the disk open: a robot that pins an upload, unpins
it and uploads again is charged nothing for what it unpinned, yet those blocks stay until a
collection finds them older than the grace period (up to two hours with the defaults). It
could write as fast as the network allowed, until the disk's reserve refused every robot's
uploads. The bytes each robot writes in a rolling hour are therefore bounded too, so what
one robot can hold of the disk at once is its pinned share plus what it wrote within the
grace period and the interval between collections.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

WINDOW_S = 3600
"""The rolling window of the write bound."""
BUCKET_S = 60
"""Writes are counted a minute at a time: at most 60 counts a robot, however many writes."""


@dataclass(frozen=True)
class Share:
    """One robot's bounds; None: no bound (a storage node, the operator's keys)."""

    max_pinned_bytes: int | None = None
    max_written_bytes_per_hour: int | None = None


UNBOUNDED = Share()


class WriteRateExceeded(Exception):
    """The upload would take the robot past the new bytes it may write in an hour; nothing
    of it is stored."""

    def __init__(self, robot: str, size: int, written: int, limit: int, retry_after_s: int):
        super().__init__(
            f"robot {robot} may write {limit} new bytes an hour and wrote {written} in the last "
            f"hour; this upload would add {size}: try again in {retry_after_s} s"
        )
        self.robot = robot
        self.size = size
        self.written = written
        self.limit = limit
        self.retry_after_s = retry_after_s


class RecentWrites:
    """The new bytes each robot wrote in the last :data:`WINDOW_S`, kept in memory: a
    restart forgets them, which only an operator can cause."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._buckets: dict[str, deque[list[int]]] = {}
        """Per robot, oldest first: ``[minute, bytes]``."""
        self._lock = threading.Lock()
        self._next_sweep = 0.0

    @contextmanager
    def charge(self, robot: str, size: int, limit: int | None) -> Iterator[None]:
        """Count ``size`` new bytes for ``robot`` while the block runs, and take them back if
        it raises (the write did not happen). :class:`WriteRateExceeded`, before the block
        runs, when they do not fit ``limit`` (None: no bound)."""
        minute = self._take(robot, size, limit)
        try:
            yield
        except BaseException:
            self._give_back(robot, minute, size)
            raise

    def add(self, robot: str, size: int, limit: int | None) -> None:
        """Count ``size`` bytes written for good (a block fetched from a peer is stored as it
        comes, with nothing to take back); :class:`WriteRateExceeded`, counting nothing, when
        they do not fit ``limit``."""
        self._take(robot, size, limit)

    def written(self, robot: str) -> int:
        with self._lock:
            return sum(count for _, count in self._current(robot))

    def _take(self, robot: str, size: int, limit: int | None) -> int:
        now = self._clock()
        minute = math.floor(now / BUCKET_S)
        with self._lock:
            self._sweep(now)
            buckets = self._current(robot, now)
            written = sum(count for _, count in buckets)
            if limit is not None and size and written + size > limit:
                raise WriteRateExceeded(
                    robot, size, written, limit, _retry_after(buckets, written + size - limit, now)
                )
            if size:
                if buckets and buckets[-1][0] == minute:
                    buckets[-1][1] += size
                else:
                    buckets.append([minute, size])
                self._buckets[robot] = buckets
            return minute

    def _give_back(self, robot: str, minute: int, size: int) -> None:
        with self._lock:
            for bucket in self._buckets.get(robot, ()):
                if bucket[0] == minute:
                    bucket[1] -= min(size, bucket[1])

    def robots(self) -> int:
        """Robots whose writes are held in memory (some may have left the window since the
        last sweep)."""
        with self._lock:
            return len(self._buckets)

    def _sweep(self, now: float) -> None:
        """Forget every robot whose writes all left the window, once a minute: one-off keys
        would otherwise be kept for good."""
        if now < self._next_sweep:
            return
        self._next_sweep = now + BUCKET_S
        for robot in list(self._buckets):
            self._current(robot, now)

    def _current(self, robot: str, now: float | None = None) -> deque[list[int]]:
        """``robot``'s buckets within the window, the older ones dropped (and the robot
        with them when none is left, so that one-off keys are not kept)."""
        buckets = self._buckets.get(robot, deque())
        now = self._clock() if now is None else now
        while buckets and _leaves_window(buckets[0][0]) <= now:
            buckets.popleft()
        if not buckets:
            self._buckets.pop(robot, None)
        return buckets


def _retry_after(buckets: deque[list[int]], excess: int, now: float) -> int:
    """Seconds until enough of the oldest writes leave the window for ``excess`` bytes more;
    the whole window when even an empty one could not hold them."""
    freed = 0
    for minute, count in buckets:
        freed += count
        if freed >= excess:
            return max(1, math.ceil(_leaves_window(minute) - now))
    return WINDOW_S


def _leaves_window(minute: int) -> int:
    """When the writes of ``minute`` stop counting: an hour after the minute's end."""
    return (minute + 1) * BUCKET_S + WINDOW_S
