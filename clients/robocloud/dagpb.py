"""dag-pb, the IPLD codec of UnixFS: a node is a list of links and an optional data field.

Nodes are written canonically (every link, then the data; each link with its hash, name and
total size) and read back with the few protobuf rules they need: varint and length-delimited
fields, nothing else. The protobuf helpers are public because UnixFS's own ``Data`` message,
carried inside a node's data field, uses the same encoding.
"""

from __future__ import annotations

import base64
import json
from collections.abc import Iterator
from dataclasses import dataclass

from robocloud.cid import CID, CIDError, decode_varint, encode_varint
from robocloud.errors import FormatError


class DagPbError(FormatError):
    """Bytes that are not a dag-pb node (or not the protobuf subset it is written in)."""


def _key(field_number: int, wire_type: int) -> bytes:
    return encode_varint(field_number << 3 | wire_type)


def len_field(field_number: int, payload: bytes) -> bytes:
    """A length-delimited protobuf field."""
    return _key(field_number, 2) + encode_varint(len(payload)) + payload


def uint_field(field_number: int, value: int) -> bytes:
    """A varint protobuf field."""
    return _key(field_number, 0) + encode_varint(value)


def fields(data: bytes) -> Iterator[tuple[int, int | bytes]]:
    """Decode protobuf fields as ``(field number, int or bytes)``; varint and length only."""
    pos = 0
    try:
        while pos < len(data):
            key, pos = decode_varint(data, pos)
            number, wire = key >> 3, key & 7
            if wire == 0:
                value, pos = decode_varint(data, pos)
                yield number, value
            elif wire == 2:
                size, pos = decode_varint(data, pos)
                if pos + size > len(data):
                    raise DagPbError(
                        f"truncated protobuf field {number}: {size} bytes declared, "
                        f"{len(data) - pos} left"
                    )
                yield number, data[pos : pos + size]
                pos += size
            else:
                raise DagPbError(f"unsupported protobuf wire type {wire} at byte {pos}")
    except ValueError as exc:
        if isinstance(exc, DagPbError):
            raise
        raise DagPbError(f"invalid protobuf at byte {pos}: {exc}") from exc


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
        links: list[Link] = []
        data: bytes | None = None
        try:
            for number, value in fields(raw):
                if number == 2 and isinstance(value, bytes):
                    links.append(_decode_link(value))
                elif number == 1 and isinstance(value, bytes):
                    data = value
                else:
                    raise DagPbError(f"unexpected dag-pb field {number}")
        except CIDError as exc:
            raise DagPbError(f"invalid dag-pb node: {exc}") from exc
        return cls(links, data)


def _decode_link(raw: bytes) -> Link:
    cid: CID | None = None
    name, tsize = "", 0
    for number, value in fields(raw):
        if number == 1 and isinstance(value, bytes):
            cid = CID.from_bytes(value)
        elif number == 2 and isinstance(value, bytes):
            try:
                name = value.decode()
            except UnicodeDecodeError as exc:
                raise DagPbError(f"a link name that is not UTF-8: {exc}") from exc
        elif number == 3 and isinstance(value, int):
            tsize = value
    if cid is None:
        raise DagPbError("dag-pb link without a hash")
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
