"""Log criteria as nodes validate them, and the filters clients poll (``eth_newFilter``).

A filter is state a stranger leaves on the node, so it is bounded as geth bounds it and
more: at most ``max_filters`` at once (a new one is refused beyond, never evicting someone
else's), of which at most ``max_per_client`` installed from one client address (one client
installing filters in a loop held every place, and every other client's were refused for as
long as it went on), each dropped when nobody has polled it for ``timeout_s`` (geth's five
minutes).
Ids are 128 random bits, so nobody polls or removes a filter they were not given.

A filter reports what changed since it was last polled: blocks mined since then (block
filters, at most ``MAX_BLOCK_HASHES`` a poll), or the logs of those blocks that match (log
filters, whole blocks up to ``index.MAX_LOG_RESULTS`` logs a poll, see
``EventIndex.logs_page``): either way the rest comes with the next poll, so a filter always
moves on. Its cursor moves only after the answer is built, so an answer that fails loses
nothing.
"""

from __future__ import annotations

import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

from services.ledger.index import LogFilter
from services.ledger.refusals import ChainError, InvalidParams

MAX_TOPICS = 4
MAX_OPTIONS = 1_000
"""Addresses, or alternatives at one topic position, in one query: each is a SQL parameter."""
MAX_BLOCK_HASHES = 10_000
"""Block hashes in one ``eth_getFilterChanges`` answer; the rest come with the next poll."""

BlockTag = int | str


@dataclass(frozen=True)
class LogCriteria:
    """What ``eth_getLogs`` and ``eth_newFilter`` were asked, tags not yet resolved.

    ``block_number`` is set with ``block_hash`` (an EIP-234 query for one block)."""

    from_block: BlockTag = "latest"
    to_block: BlockTag = "latest"
    addresses: tuple[bytes, ...] = ()
    topics: tuple[tuple[bytes, ...] | None, ...] = ()
    block_hash: bytes | None = None
    block_number: int | None = None

    def __post_init__(self) -> None:
        if len(self.topics) > MAX_TOPICS:
            raise InvalidParams("exceeded maximum topics len")
        if len(self.addresses) > MAX_OPTIONS:
            raise InvalidParams(f"too many addresses: at most {MAX_OPTIONS}")
        for options in self.topics:
            if options is not None and len(options) > MAX_OPTIONS:
                raise InvalidParams(f"too many topics at one position: at most {MAX_OPTIONS}")

    def resolve(self, head: int) -> LogFilter:
        """The block range at ``head``: named tags are the head (every block is final), a
        range ending past the head ends at it, one starting past it is refused as anvil does."""
        if self.block_number is not None:
            first = last = self.block_number
        else:
            first = _number(self.from_block, head)
            last = min(_number(self.to_block, head), head)
            if first > head:
                raise InvalidParams(
                    f"BlockOutOfRangeError: block height is {head} but requested was {first}"
                )
        return LogFilter(
            from_block=first,
            to_block=last,
            addresses=self.addresses,
            topics=self.topics,
            block_hash=self.block_hash,
        )

    def window(self, first: int, last: int) -> LogFilter | None:
        """The part of blocks ``first`` to ``last`` a filter with these criteria watches: a
        named tag bounds nothing (``latest`` means "as the chain grows"), a number does."""
        if self.block_number is not None:
            first, last = max(first, self.block_number), min(last, self.block_number)
        if isinstance(self.from_block, int):
            first = max(first, self.from_block)
        if isinstance(self.to_block, int):
            last = min(last, self.to_block)
        if first > last:
            return None
        return LogFilter(first, last, self.addresses, self.topics, self.block_hash)


def _number(tag: BlockTag, head: int) -> int:
    if tag == "earliest":
        return 0
    return head if isinstance(tag, str) else tag


class FilterNotFound(ChainError):
    """Unknown, expired or uninstalled: geth's and anvil's ``filter not found``."""

    def __init__(self) -> None:
        super().__init__("filter not found")


class TooManyFilters(ChainError):
    def __init__(self, limit: int, *, from_client: bool = False) -> None:
        whose = " from one client" if from_client else ""
        super().__init__(
            f"too many filters{whose}: at most {limit} at once; uninstall filters no longer polled"
        )


@dataclass(frozen=True)
class Installed:
    """One filter: ``criteria`` None for a block filter; ``reported`` the last block whose
    changes were answered."""

    criteria: LogCriteria | None
    reported: int
    deadline: float
    client: str | None = None
    """Who installed it (``services.common.slots.client_key``); None: the node itself."""


@dataclass(frozen=True)
class Changes:
    """What a poll is to report: blocks ``first`` to ``last`` (none when first > last)."""

    criteria: LogCriteria | None
    first: int
    last: int


class Filters:
    """The installed filters, bounded in number and lifetime; thread-safe."""

    def __init__(
        self,
        max_filters: int,
        timeout_s: float,
        clock: Callable[[], float] = time.monotonic,
        max_per_client: int | None = None,
    ) -> None:
        self.max_filters = max_filters
        self.max_per_client = max_filters if max_per_client is None else max_per_client
        self.timeout_s = timeout_s
        self._clock = clock
        self._lock = threading.Lock()
        self._filters: dict[str, Installed] = {}

    def __len__(self) -> int:
        with self._lock:
            self._expire()
            return len(self._filters)

    def install(self, criteria: LogCriteria | None, head: int, client: str | None = None) -> str:
        """A new filter reporting what happens after block ``head``, for ``client``; its id."""
        with self._lock:
            self._expire()
            if len(self._filters) >= self.max_filters:
                raise TooManyFilters(self.max_filters)
            if client is not None and self._installed_by(client) >= self.max_per_client:
                raise TooManyFilters(self.max_per_client, from_client=True)
            filter_id = "0x" + secrets.token_hex(16)
            deadline = self._clock() + self.timeout_s
            self._filters[filter_id] = Installed(criteria, head, deadline, client)
            return filter_id

    def _installed_by(self, client: str) -> int:
        return sum(installed.client == client for installed in self._filters.values())

    def changes(self, filter_id: str, head: int) -> Changes:
        """What ``filter_id`` has to report at ``head`` (call ``reported`` once answered)."""
        with self._lock:
            installed = self._get(filter_id)
            last = head
            if installed.criteria is None:
                last = min(head, installed.reported + MAX_BLOCK_HASHES)
            self._filters[filter_id] = replace(installed, deadline=self._clock() + self.timeout_s)
            return Changes(installed.criteria, installed.reported + 1, last)

    def reported(self, filter_id: str, last: int) -> None:
        """Blocks up to ``last`` were answered to ``filter_id``."""
        with self._lock:
            installed = self._filters.get(filter_id)
            if installed is not None and last > installed.reported:
                self._filters[filter_id] = replace(installed, reported=last)

    def criteria(self, filter_id: str) -> LogCriteria:
        """A log filter's criteria (``eth_getFilterLogs``); block filters have none."""
        with self._lock:
            installed = self._get(filter_id)
            if installed.criteria is None:
                raise FilterNotFound()
            self._filters[filter_id] = replace(installed, deadline=self._clock() + self.timeout_s)
            return installed.criteria

    def uninstall(self, filter_id: str) -> bool:
        with self._lock:
            self._expire()
            return self._filters.pop(filter_id, None) is not None

    def _get(self, filter_id: str) -> Installed:
        self._expire()
        installed = self._filters.get(filter_id)
        if installed is None:
            raise FilterNotFound()
        return installed

    def _expire(self) -> None:
        now = self._clock()
        for filter_id in [key for key, value in self._filters.items() if value.deadline < now]:
            del self._filters[filter_id]
