"""DAG-JSON links: the CIDs a dag-json block points to.

Pinning, garbage collection and ``dag/export`` follow a DAG whatever its codecs, as kubo's
recursive pin and ``dag export`` do (go-ipld-prime decodes dag-json links as it decodes
dag-cbor's). In dag-json a link is a map with the one key ``"/"`` whose value is the CID as
a string; ``{"/": {"bytes": ...}}`` is a byte string, not a link. The block is parsed with
:mod:`robocloud.bounded_json` (64 levels, checked before the recursive C parser runs), and
the parsed document is walked with a stack, not by recursion.
"""

from __future__ import annotations

from typing import Any

from robocloud import bounded_json
from robocloud.cid import CID, CIDError, parse_cid
from robocloud.errors import FormatError


class DagJsonError(FormatError):
    """Bytes that are not dag-json: not JSON, nested past the bound, or a bad link."""


def links(data: bytes) -> list[CID]:
    """The CIDs ``data`` links to, in document order (a repeated link every time)."""
    try:
        document = bounded_json.loads(data)
    except FormatError as exc:
        raise DagJsonError(f"not dag-json: {exc}") from exc
    found: list[CID] = []
    stack: list[Any] = [document]
    while stack:
        value = stack.pop()
        if isinstance(value, dict):
            if len(value) == 1 and isinstance(value.get("/"), str):
                found.append(_link(value["/"]))
                continue
            stack.extend(reversed(list(value.values())))
        elif isinstance(value, list):
            stack.extend(reversed(value))
    return found


def _link(text: str) -> CID:
    try:
        return parse_cid(text)
    except CIDError as exc:
        raise DagJsonError(f"a link that is not a CID: {exc}") from exc
