"""dag-pb, the IPLD codec of UnixFS: a node is a list of links and an optional data field.

Nodes are written canonically (every link, then the data; each link with its hash, name and
total size) and read as strictly as the IPLD dag-pb specification asks of a decoder, so that
one block has one meaning everywhere: ``PBLink`` fields in field-number order, no field twice,
no field or wire type outside the schema, a ``Hash`` in every link, and the links in one run
(before or after ``Data``: IPFS data exists in both orders, never interleaved). Every length
and count is checked against the bytes actually there before anything is allocated, and a
node may hold at most :data:`MAX_LINKS` links, so a hostile block costs time in proportion
to its size and nothing more.

The protobuf helpers are public because UnixFS's own ``Data`` message, carried inside a
node's data field, uses the same encoding.
"""

from __future__ import annotations

import base64
import json
from collections.abc import Iterator
from dataclasses import dataclass

from robocloud.cid import CID, CIDError, encode_varint
from robocloud.errors import FormatError

MAX_VARINT_BYTES = 10
"""Protobuf's varint limit: 10 bytes hold a uint64, more is not protobuf."""
MAX_LINKS = 1 << 16
"""Most links one node may hold. Importers write at most 1,024 per file node (174 by
default), HAMT directory shards at most 1,024 (256 by default), and kubo shards a plain
directory once its block passes 256 KiB (some 6,000 entries); a 2 MiB block, twice what
bitswap exchanges, holds at most about 50,000 links of the smallest size."""

_LENGTH_DELIMITED = 2
_VARINT = 0


class DagPbError(FormatError):
    """Bytes that are not a dag-pb node (or not the protobuf subset it is written in)."""


def _key(field_number: int, wire_type: int) -> bytes:
    return encode_varint(field_number << 3 | wire_type)


def len_field(field_number: int, payload: bytes) -> bytes:
    """A length-delimited protobuf field."""
    return _key(field_number, _LENGTH_DELIMITED) + encode_varint(len(payload)) + payload


def uint_field(field_number: int, value: int) -> bytes:
    """A varint protobuf field."""
    return _key(field_number, _VARINT) + encode_varint(value)


def read_uint(data: bytes, pos: int, end: int) -> tuple[int, int]:
    """The protobuf varint (a uint64) at ``pos``, not reading past ``end``; and what follows."""
    if pos < end and data[pos] < 0x80:  # keys, lengths and sizes under 128: most of them
        return data[pos], pos + 1
    value = shift = 0
    for index in range(pos, min(end, pos + MAX_VARINT_BYTES)):
        byte = data[index]
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            if value >> 64:
                raise DagPbError(f"varint at byte {pos} does not fit in 64 bits")
            return value, index + 1
        shift += 7
    if end - pos >= MAX_VARINT_BYTES:
        raise DagPbError(f"varint at byte {pos} is longer than {MAX_VARINT_BYTES} bytes")
    raise DagPbError(f"varint at byte {pos} runs past the end of its message at byte {end}")


def _read_length(
    data: bytes, pos: int, end: int, at: int, field: str, link: int | None = None
) -> tuple[int, int]:
    """The bounds ``(start, stop)`` of the payload of ``field`` (whose key is at ``at``, its
    length at ``pos``), refused when it would run past ``end``."""
    size, start = read_uint(data, pos, end)
    if size > end - start:
        owner = "" if link is None else f"link {link}'s "
        raise DagPbError(
            f"{owner}{field} at byte {at} declares {size} bytes but only {end - start} are left"
        )
    return start, start + size


def fields(data: bytes) -> Iterator[tuple[int, int | bytes]]:
    """Decode protobuf fields as ``(field number, int or bytes)``; varint and length only."""
    pos, end = 0, len(data)
    while pos < end:
        at = pos
        key, pos = read_uint(data, pos, end)
        number, wire = key >> 3, key & 7
        if wire == _VARINT:
            value, pos = read_uint(data, pos, end)
            yield number, value
        elif wire == _LENGTH_DELIMITED:
            start, pos = _read_length(data, pos, end, at, f"field {number}")
            yield number, data[start:pos]
        else:
            raise DagPbError(f"field {number} at byte {at} has unsupported wire type {wire}")


@dataclass
class Link:
    """One link of a node: the child's CID, its name in a directory, its cumulative size."""

    cid: CID
    name: str
    tsize: int


@dataclass
class PBNode:
    links: list[Link]
    data: bytes | None

    def encode(self) -> bytes:
        """dag-pb's canonical order: every link, then the data."""
        out = bytearray()
        for link in self.links:
            body = len_field(1, link.cid.binary) + len_field(2, link.name.encode())
            body += uint_field(3, link.tsize)
            out += len_field(2, body)
        if self.data is not None:
            out += len_field(1, self.data)
        return bytes(out)

    @classmethod
    def decode(cls, raw: bytes) -> PBNode:
        """A node from its block; :class:`DagPbError` names the byte and field at fault."""
        links: list[Link] = []
        data: bytes | None = None
        links_closed = False
        pos, end = 0, len(raw)
        while pos < end:
            at = pos
            key, pos = read_uint(raw, pos, end)
            number, wire = key >> 3, key & 7
            if number not in (1, 2):
                raise DagPbError(f"PBNode field {number} at byte {at}: only Data (1) and Links (2)")
            if wire != _LENGTH_DELIMITED:
                raise DagPbError(f"PBNode field {number} at byte {at} has wire type {wire}, not 2")
            start, pos = _read_length(raw, pos, end, at, "Data" if number == 1 else "a link")
            if number == 1:
                if data is not None:
                    raise DagPbError(f"a second Data field at byte {at}")
                data = raw[start:pos]
                links_closed = bool(links)
            elif links_closed:
                raise DagPbError(f"a link at byte {at} after the Data that follows the links")
            elif len(links) == MAX_LINKS:
                raise DagPbError(f"more than {MAX_LINKS} links (the limit) at byte {at}")
            else:
                links.append(_decode_link(raw, start, pos, len(links)))
        return cls(links, data)


_LINK_FIELDS = {1: ("Hash", _LENGTH_DELIMITED), 2: ("Name", _LENGTH_DELIMITED), 3: ("Tsize", 0)}


def _decode_link(raw: bytes, pos: int, end: int, index: int) -> Link:
    """Link ``index``, the PBLink message in ``raw[pos:end]``."""
    cid: CID | None = None
    name, tsize = "", 0
    last = 0
    while pos < end:
        at = pos
        key, pos = read_uint(raw, pos, end)
        number, wire = key >> 3, key & 7
        if number not in _LINK_FIELDS:
            raise DagPbError(f"link {index}: field {number} at byte {at} is not in PBLink")
        field_name, expected_wire = _LINK_FIELDS[number]
        if wire != expected_wire:
            raise DagPbError(
                f"link {index}: {field_name} at byte {at} has wire type {wire}, not {expected_wire}"
            )
        if number <= last:
            raise DagPbError(
                f"link {index}: {field_name} at byte {at} repeats or comes after "
                f"{_LINK_FIELDS[last][0]}"
            )
        last = number
        if number == 3:
            tsize, pos = read_uint(raw, pos, end)
            continue
        start, pos = _read_length(raw, pos, end, at, field_name, index)
        if number == 1:
            try:
                cid = CID.from_bytes(raw[start:pos])
            except CIDError as exc:
                raise DagPbError(f"link {index}: Hash at byte {start}: {exc}") from exc
        else:
            try:
                name = raw[start:pos].decode()
            except UnicodeDecodeError as exc:
                raise DagPbError(f"link {index}: Name at byte {start} is not UTF-8") from exc
    if cid is None:
        raise DagPbError(f"link {index} has no Hash")
    return Link(cid, name, tsize)


def to_dag_json(node: PBNode) -> bytes:
    """The node in DAG-JSON (``application/vnd.ipld.dag-json``), as kubo's gateway renders it.

    The dag-pb data model: ``Data`` (bytes, as ``{"/": {"bytes": <base64, no padding>}}``)
    when present, ``Links`` with ``Hash`` (``{"/": <cid>}``), ``Name`` and ``Tsize``; map keys in
    byte order and no whitespace, as DAG-JSON requires.
    """
    document: dict[str, object] = {}
    if node.data is not None:
        encoded = base64.b64encode(node.data).decode().rstrip("=")
        document["Data"] = {"/": {"bytes": encoded}}
    document["Links"] = [
        {"Hash": {"/": str(link.cid)}, "Name": link.name, "Tsize": link.tsize}
        for link in node.links
    ]
    return json.dumps(document, separators=(",", ":"), ensure_ascii=False).encode()
