"""DAG-CBOR links: the CIDs a dag-cbor block points to, found without building its values.

Pinning, garbage collection and ``dag/export`` follow a DAG whatever its codecs, as kubo's
recursive pin and ``dag export`` do; from a dag-cbor block they need its links (CBOR tag 42
over a byte string: ``0x00``, then the binary CID), not its values. :func:`links` reads the
CBOR items in one pass, keeping a count of the items each open container still holds
instead of recursing; it takes the nesting go-ipld-prime (kubo's decoder) takes, 1,024
levels, and refuses the 1,025th, so cas pins what kubo pins and no more. A container may
claim no more items than bytes are left, so the work is linear in the block's size whatever
its header says.

It checks the framing dag-cbor allows (definite lengths, tag 42 only, the simple values
false, true, null and floats) but not canonical form (key order, shortest integers): it
finds links, it does not validate documents. A general CBOR decoder (cbor2) would build
every value and recurse once per level, the overflow ``bounded_json`` exists to avoid.
"""

from __future__ import annotations

from robocloud.cid import CID, CIDError
from robocloud.dagjson import MAX_DEPTH
from robocloud.errors import FormatError

CID_TAG = 42
_WIDTHS = {24: 1, 25: 2, 26: 4, 27: 8}
_SIMPLE = frozenset({20, 21, 22, 25, 26, 27})
"""Major type 7 as dag-cbor has it: false, true, null, and half, single, double floats."""


class DagCborError(FormatError):
    """Bytes that are not dag-cbor: truncated, trailing bytes, or CBOR that dag-cbor forbids."""


def links(data: bytes) -> list[CID]:
    """The CIDs ``data`` links to, in the order they appear (a repeated link every time)."""
    found: list[CID] = []
    pos = 0
    due = 1
    holding: list[int] = []
    """Items still to read in each open container, the innermost last."""
    while due:
        due -= 1
        if holding:
            holding[-1] -= 1
        at = pos
        major, info, value, pos = _head(data, pos)
        if major in (2, 3):
            if value > len(data) - pos:
                raise DagCborError(f"byte {at}: a {value}-byte string, {len(data) - pos} left")
            pos += value
        elif major in (4, 5):
            if len(holding) >= MAX_DEPTH:
                raise DagCborError(f"byte {at}: nested deeper than {MAX_DEPTH} levels")
            items = value * (2 if major == 5 else 1)
            due += items
            if due > len(data) - pos:
                raise DagCborError(
                    f"byte {at}: a container of {value} items, {len(data) - pos} bytes left"
                )
            holding.append(items)
        elif major == 6:
            if value != CID_TAG:
                raise DagCborError(f"byte {at}: tag {value}; dag-cbor has only tag 42 (a CID)")
            cid, pos = _link(data, pos)
            found.append(cid)
        elif major == 7 and info not in _SIMPLE:
            raise DagCborError(f"byte {at}: simple value {info} is not dag-cbor")
        while holding and not holding[-1]:
            holding.pop()
    if pos != len(data):
        raise DagCborError(f"{len(data) - pos} bytes after the dag-cbor item")
    return found


def _head(data: bytes, pos: int) -> tuple[int, int, int, int]:
    """``(major type, additional info, argument, offset after the head)`` of the item at ``pos``."""
    if pos >= len(data):
        raise DagCborError(f"truncated: an item is missing at byte {pos}")
    major, info = data[pos] >> 5, data[pos] & 0x1F
    if info < 24:
        return major, info, info, pos + 1
    width = _WIDTHS.get(info)
    if width is None:
        raise DagCborError(
            f"byte {pos}: indefinite or reserved lengths (additional info {info}) are not dag-cbor"
        )
    end = pos + 1 + width
    if end > len(data):
        raise DagCborError(f"truncated: the argument of the item at byte {pos}")
    return major, info, int.from_bytes(data[pos + 1 : end], "big"), end


def _link(data: bytes, pos: int) -> tuple[CID, int]:
    """The CID under a tag 42 whose content starts at ``pos``: ``0x00`` + a binary CID."""
    major, _, size, start = _head(data, pos)
    end = start + size
    if major != 2 or size == 0 or end > len(data) or data[start] != 0:
        raise DagCborError(f"byte {pos}: tag 42 must hold a byte string of 0x00 and a CID")
    try:
        return CID.from_bytes(data[start + 1 : end]), end
    except CIDError as exc:
        raise DagCborError(f"byte {pos}: invalid link: {exc}") from exc
