"""Owned pins: which robot keeps which DAG alive.

A pin is a (root CID, owner address) pair: several robots may pin the same content, and
each may remove only its own pin, so one robot can never make another's data collectable.
Every change is appended to a journal fsynced before the request is answered, one line a
request whatever its number of roots: a torn last line is dropped on read, so a crash in the
middle of a many-root ``pin/add`` or ``block/put`` leaves none of its pins rather than the
first few, and the request costs one fsync instead of one a root. A start compacts the
journal only when it holds many dead lines, and starts all the same when it cannot: a
start that needs no free space lets an operator restart a cas on a full disk to collect
garbage.
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Sequence
from pathlib import Path

from robocloud.cid import CID
from services.common.durable import AppendLog

log = logging.getLogger("robocloud.cas.pins")


class NotPinned(LookupError):
    def __init__(self, cid: CID) -> None:
        super().__init__(f"{cid} is not pinned")
        self.cid = cid


class PinNotOwned(PermissionError):
    """Only other robots pinned it: one robot never removes another's pin."""

    def __init__(self, cid: CID, owner: str) -> None:
        super().__init__(f"{cid} is pinned by other robots; {owner} can only remove its own pins")
        self.cid = cid
        self.owner = owner


class PinSet:
    def __init__(self, path: Path) -> None:
        self._log = AppendLog(path)
        self._owners: dict[CID, set[str]] = {}
        self._lock = threading.Lock()
        lines = self._log.read_lines()
        for line in lines:
            entry = json.loads(line)
            for cid in entry["cids"] if "cids" in entry else [entry["cid"]]:
                self._apply(entry["op"], CID.decode(cid), entry["owner"])
        self._log.compact_at_open(self._live_lines(), len(lines))

    def _live_lines(self) -> list[str]:
        """The pins as a compacted journal holds them: one line per owner."""
        by_owner: dict[str, list[CID]] = {}
        for cid, owners in self._owners.items():
            for owner in owners:
                by_owner.setdefault(owner, []).append(cid)
        return [self._line("add", cids, owner) for owner, cids in by_owner.items()]

    @staticmethod
    def _line(op: str, cids: Sequence[CID], owner: str) -> str:
        """One journal line; older journals wrote ``"cid"``, one root a line, read as well."""
        document = {"op": op, "cids": [str(cid) for cid in cids], "owner": owner}
        return json.dumps(document, separators=(",", ":"))

    def _apply(self, op: str, cid: CID, owner: str) -> None:
        if op == "add":
            self._owners.setdefault(cid, set()).add(owner)
            return
        owners = self._owners.get(cid, set())
        owners.discard(owner)
        if not owners:
            self._owners.pop(cid, None)

    def add_all(self, cids: list[CID], owner: str) -> list[CID]:
        """Pin every CID for ``owner`` in one turn of the lock; returns those newly pinned.

        The caller checks every DAG first, so a request either pins all its roots or none.
        """
        with self._lock:
            new = [cid for cid in dict.fromkeys(cids) if owner not in self._owners.get(cid, ())]
            if new:
                self._log.append(self._line("add", new, owner))
            for cid in new:
                self._apply("add", cid, owner)
            return new

    def remove(self, cids: list[CID], owner: str) -> None:
        """Remove ``owner``'s pins on every CID, or none of them.

        :class:`NotPinned` if nobody pinned one of them, :class:`PinNotOwned` if only other
        robots did.
        """
        with self._lock:
            for cid in cids:
                self._check_removable(cid, owner)
            if cids:
                self._log.append(self._line("rm", cids, owner))
            for cid in cids:
                self._apply("rm", cid, owner)

    def _check_removable(self, cid: CID, owner: str) -> None:
        owners = self._owners.get(cid)
        if not owners:
            raise NotPinned(cid)
        if owner not in owners:
            raise PinNotOwned(cid, owner)

    def owners(self, cid: CID) -> frozenset[str]:
        with self._lock:
            return frozenset(self._owners.get(cid, ()))

    def snapshot(self) -> dict[CID, frozenset[str]]:
        with self._lock:
            return {cid: frozenset(owners) for cid, owners in self._owners.items()}

    def close(self) -> None:
        self._log.close()
