"""Owned pins: which robot keeps which DAG alive, and how many bytes it keeps.

A pin is a (root CID, owner address) pair: several robots may pin the same content, and
each may remove only its own pin, so one robot can never make another's data collectable.
Each pin carries the bytes its owner was charged for it, its DAG's cumulative size (kubo's
``CumulativeSize``), and a robot's pins together may hold at most its share
(``ROBOCLOUD_CAS_MAX_PINNED_BYTES_PER_ROBOT``): without one, a single registered robot
could fill the disk that every robot's data lives on. Removing a pin gives its charge back.
Two robots pinning the same DAG are each charged for it, as each alone keeps it alive.
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
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

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


class PinQuotaExceeded(Exception):
    """The pins would take the robot past its share of pinned bytes; none of them is made."""

    def __init__(self, owner: str, size: int, used: int, limit: int) -> None:
        super().__init__(
            f"robot {owner} may keep {limit} bytes pinned and keeps {used}; these pins would add "
            f"{size}: remove some of its pins (pin/rm) first"
        )
        self.owner = owner
        self.size = size
        self.used = used
        self.limit = limit


class PinSet:
    """The pins, their owners and the bytes each owner was charged, kept in a journal.

    ``dag_bytes`` charges the pins of journals written before charges were kept, once, at
    open: the journal is then rewritten with their charges.
    """

    def __init__(self, path: Path, dag_bytes: Callable[[CID], int] | None = None) -> None:
        self._log = AppendLog(path)
        self._charges: dict[CID, dict[str, int]] = {}
        """Per root: each owner and the bytes it was charged for its pin."""
        self._used: dict[str, int] = {}
        self._lock = threading.Lock()
        lines = self._log.read_lines()
        uncharged = [self._replay(json.loads(line), dag_bytes) for line in lines]
        self._log.compact_at_open(self._live_lines(), len(lines), force=any(uncharged))

    def _replay(self, entry: dict[str, Any], dag_bytes: Callable[[CID], int] | None) -> bool:
        """Apply one journal line; True when it is an ``add`` from before charges were kept."""
        cids = [CID.decode(cid) for cid in entry.get("cids", [entry.get("cid")])]
        if entry["op"] == "rm":
            for cid in cids:
                self._unpin(cid, entry["owner"])
            return False
        charges = entry.get("bytes")
        if charges is None:
            charges = [dag_bytes(cid) if dag_bytes else 0 for cid in cids]
        for cid, charge in zip(cids, charges, strict=True):
            self._pin(cid, entry["owner"], charge)
        return "bytes" not in entry

    def _live_lines(self) -> list[str]:
        """The pins as a compacted journal holds them: one line per owner."""
        by_owner: dict[str, dict[CID, int]] = {}
        for cid, owners in self._charges.items():
            for owner, charge in owners.items():
                by_owner.setdefault(owner, {})[cid] = charge
        return [self._add_line(charges, owner) for owner, charges in by_owner.items()]

    @staticmethod
    def _add_line(charges: Mapping[CID, int], owner: str) -> str:
        """An ``add`` line: the roots, and in ``bytes`` what each was charged. Older journals
        wrote ``"cid"``, one root a line, and no charges: they are read as well."""
        document = {
            "op": "add",
            "cids": [str(cid) for cid in charges],
            "bytes": list(charges.values()),
            "owner": owner,
        }
        return json.dumps(document, separators=(",", ":"))

    @staticmethod
    def _remove_line(cids: Sequence[CID], owner: str) -> str:
        document = {"op": "rm", "cids": [str(cid) for cid in cids], "owner": owner}
        return json.dumps(document, separators=(",", ":"))

    def _pin(self, cid: CID, owner: str, charge: int) -> None:
        owners = self._charges.setdefault(cid, {})
        self._used[owner] = self._used.get(owner, 0) - owners.get(owner, 0) + charge
        owners[owner] = charge

    def _unpin(self, cid: CID, owner: str) -> None:
        owners = self._charges.get(cid, {})
        charge = owners.pop(owner, None)
        if charge is not None:
            used = self._used.get(owner, 0) - charge
            if used:
                self._used[owner] = used
            else:
                self._used.pop(owner, None)
        if not owners:
            self._charges.pop(cid, None)

    def add_all(
        self, charges: Mapping[CID, int], owner: str, *, max_bytes: int | None = None
    ) -> list[CID]:
        """Pin every root of ``charges`` for ``owner``, charged the bytes given for it, in
        one turn of the lock; returns those newly pinned. A root ``owner`` already pinned
        is neither pinned nor charged again.

        :class:`PinQuotaExceeded`, with nothing pinned, when the new ones would take
        ``owner`` past ``max_bytes`` (None: no bound). The caller checks every DAG first,
        so a request either pins all its roots or none.
        """
        with self._lock:
            new = self._new(charges, owner)
            self._check_share(new, owner, max_bytes)
            if new:
                self._log.append(self._add_line(new, owner))
            for cid, charge in new.items():
                self._pin(cid, owner, charge)
            return list(new)

    def check_share(self, charges: Mapping[CID, int], owner: str, *, max_bytes: int | None) -> None:
        """Raise :class:`PinQuotaExceeded` if pinning ``charges`` now would: asked before a
        request's blocks are stored, so a refused request stores nothing. ``add_all`` asks
        again, for pins of the same robot made in between."""
        with self._lock:
            new = self._new(charges, owner)
            self._check_share(new, owner, max_bytes)

    def _new(self, charges: Mapping[CID, int], owner: str) -> dict[CID, int]:
        """The roots of ``charges`` that ``owner`` does not pin yet: only those are charged."""
        return {
            cid: charge
            for cid, charge in charges.items()
            if owner not in self._charges.get(cid, ())
        }

    def _check_share(self, new: Mapping[CID, int], owner: str, max_bytes: int | None) -> None:
        size = sum(new.values())
        used = self._used.get(owner, 0)
        if max_bytes is not None and size and used + size > max_bytes:
            raise PinQuotaExceeded(owner, size, used, max_bytes)

    def remove(self, cids: list[CID], owner: str) -> None:
        """Remove ``owner``'s pins on every CID, or none of them; their charges go back.

        :class:`NotPinned` if nobody pinned one of them, :class:`PinNotOwned` if only other
        robots did.
        """
        with self._lock:
            for cid in cids:
                self._check_removable(cid, owner)
            if cids:
                self._log.append(self._remove_line(cids, owner))
            for cid in cids:
                self._unpin(cid, owner)

    def _check_removable(self, cid: CID, owner: str) -> None:
        owners = self._charges.get(cid)
        if not owners:
            raise NotPinned(cid)
        if owner not in owners:
            raise PinNotOwned(cid, owner)

    def owners(self, cid: CID) -> frozenset[str]:
        with self._lock:
            return frozenset(self._charges.get(cid, ()))

    def pinned_bytes(self, owner: str) -> int:
        """The bytes ``owner``'s pins were charged, together."""
        with self._lock:
            return self._used.get(owner, 0)

    def snapshot(self) -> dict[CID, frozenset[str]]:
        with self._lock:
            return {cid: frozenset(owners) for cid, owners in self._charges.items()}

    def close(self) -> None:
        self._log.close()
