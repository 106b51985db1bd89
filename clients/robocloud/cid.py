"""Content identifiers (CIDv0 and CIDv1) with sha2-256 and identity multihashes.

A robot trusts nothing but the CID: :meth:`CID.verify` is the check every fetched block
passes. Text forms are multibase base32 lower case (``b...``) for CIDv1 and base58btc
(``Qm...``) for CIDv0; ``z`` (base58btc) and ``f`` (base16) CIDv1 text is accepted as input.
"""

from __future__ import annotations

import base64
import hashlib
import re
from dataclasses import dataclass
from typing import NamedTuple

from robocloud.errors import FormatError

RAW = 0x55
DAG_PB = 0x70
DAG_CBOR = 0x71
DAG_JSON = 0x0129
SHA2_256 = 0x12
IDENTITY = 0x00
CODEC_NAMES = {RAW: "raw", DAG_PB: "dag-pb", DAG_CBOR: "dag-cbor"}
MAX_IDENTITY_DIGEST = 128
MAX_CID_TEXT = 512
"""Longer text is refused unparsed: base58 decoding is quadratic in the length."""
_B58 = "123456789ABCDEFGHJKLMNPQRSTUVWXYZabcdefghijkmnopqrstuvwxyz"
_B58_INDEX = {c: i for i, c in enumerate(_B58)}


class CIDError(FormatError):
    """A CID that cannot be parsed, or a block that does not match its CID.

    ``text`` is the text that failed to parse and ``field`` where it came from (a query
    parameter, a path segment, a JSON field), when :func:`parse_cid` knows them.
    """

    def __init__(self, message: str, *, text: str | None = None, field: str | None = None) -> None:
        super().__init__(message)
        self.text = text
        self.field = field


def parse_cid(text: str, field: str | None = None) -> CID:
    """The one way text from outside becomes a CID; the error quotes it and names ``field``."""
    if len(text) > MAX_CID_TEXT:
        raise CIDError(
            f"invalid CID: {len(text)} characters, more than {MAX_CID_TEXT}",
            text=text[:64] + "...",
            field=field,
        )
    try:
        return CID.decode(text)
    except CIDError as exc:
        raise CIDError(str(exc), text=text, field=field) from exc


MAX_VARINT_BYTES = 9
"""The multiformats unsigned-varint limit (63 bits): longer ones are not CID varints."""


class VarintError(FormatError):
    """A multiformats varint that is truncated, longer than 9 bytes or not minimally encoded."""


def encode_varint(value: int) -> bytes:
    """Unsigned LEB128, as multiformats and protobuf use it."""
    if value < 0:
        raise ValueError("varints are unsigned")
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def decode_varint(data: bytes | memoryview, offset: int = 0) -> tuple[int, int]:
    """``(value, next offset)`` of the multiformats unsigned-varint at ``offset``.

    The multiformats spec (and go-varint, which reads CIDs and CAR sections in Go) allows at
    most 9 bytes and only the minimal encoding, so that every value has exactly one binary
    form: a CID read back from bytes then re-encodes to the same bytes.
    """
    if offset < len(data) and data[offset] < 0x80:
        return data[offset], offset + 1
    value = shift = 0
    for index in range(offset, min(len(data), offset + MAX_VARINT_BYTES)):
        byte = data[index]
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            if byte == 0 and index > offset:
                raise VarintError(f"varint at byte {offset} is not minimally encoded")
            return value, index + 1
        shift += 7
    if len(data) - offset > MAX_VARINT_BYTES:
        raise VarintError(f"varint at byte {offset} is longer than {MAX_VARINT_BYTES} bytes")
    raise VarintError(f"varint at byte {offset} is truncated")


def b58encode(data: bytes) -> str:
    number = int.from_bytes(data, "big")
    out = ""
    while number:
        number, rem = divmod(number, 58)
        out = _B58[rem] + out
    return "1" * (len(data) - len(data.lstrip(b"\0"))) + out


def b58decode(text: str) -> bytes:
    number = 0
    for char in text:
        if char not in _B58_INDEX:
            raise ValueError(f"{char!r} is not a base58btc character")
        number = number * 58 + _B58_INDEX[char]
    body = number.to_bytes((number.bit_length() + 7) // 8, "big")
    return b"\0" * (len(text) - len(text.lstrip("1"))) + body


_BASE32 = re.compile(r"[A-Za-z2-7]*")
_BASE16 = re.compile(r"[0-9A-Fa-f]*")
_ALPHABETS = {"b": _BASE32, "B": _BASE32, "f": _BASE16, "F": _BASE16}
"""Each multibase's characters as go-multibase (kubo's) takes them, either case: Python's
decoders also took padding (``=``) and hex with spaces between its bytes, which it refuses."""


@dataclass(frozen=True, slots=True)
class CID:
    """A parsed CID; ``multihash`` holds the whole multihash (code, length, digest)."""

    version: int
    codec: int
    multihash: bytes

    @classmethod
    def decode(cls, text: str) -> CID:
        """Parse a CID's text form, raising :class:`CIDError` that quotes it."""
        if len(text) > MAX_CID_TEXT:
            raise CIDError(f"invalid CID: {len(text)} characters, more than {MAX_CID_TEXT}")
        try:
            if len(text) == 46 and text.startswith("Qm"):
                return cls.from_bytes(b58decode(text))
            prefix, body = text[:1], text[1:]
            alphabet = _ALPHABETS.get(prefix)
            if alphabet is not None and not alphabet.fullmatch(body):
                raise ValueError(f"a character outside multibase {prefix!r}'s alphabet")
            if prefix in ("b", "B"):
                binary = base64.b32decode(body.upper() + "=" * (-len(body) % 8))
            elif prefix == "z":
                binary = b58decode(body)
            elif prefix in ("f", "F"):
                binary = bytes.fromhex(body)
            else:
                raise ValueError("unsupported multibase prefix")
            cid = cls.from_bytes(binary)
        except (ValueError, TypeError) as exc:
            raise CIDError(f"invalid CID {text!r}: {exc}") from exc
        if cid.version == 0:
            raise CIDError(f"invalid CID {text!r}: CIDv0 is only written in base58btc")
        return cid

    @classmethod
    def from_bytes(cls, binary: bytes) -> CID:
        """Parse a binary CID (as stored on chain and in CAR files)."""
        cid, end = cls.read(binary, 0)
        if end != len(binary):
            raise CIDError(f"{len(binary) - end} trailing bytes after the CID")
        return cid

    @classmethod
    def read(cls, data: bytes | memoryview, offset: int) -> tuple[CID, int]:
        """Parse a binary CID at ``offset``; return it and the offset after it."""
        end = offset + 36
        if (  # the common case first: CIDv1, a one-byte codec, sha2-256
            end <= len(data)
            and data[offset] == 1
            and data[offset + 1] < 0x80
            and data[offset + 2 : offset + 4] == b"\x12\x20"
        ):
            return cls(1, data[offset + 1], bytes(data[offset + 2 : end])), end
        try:
            if data[offset : offset + 2] == b"\x12\x20":
                end = offset + 34
                if end > len(data):
                    raise ValueError("truncated CIDv0")
                return cls(0, DAG_PB, bytes(data[offset:end])), end
            version, pos = decode_varint(data, offset)
            if version != 1:
                raise ValueError(f"unsupported CID version {version}")
            codec, pos = decode_varint(data, pos)
            code, digest_at = decode_varint(data, pos)
            size, digest_at = decode_varint(data, digest_at)
            _check_multihash(code, size)
        except ValueError as exc:
            raise CIDError(f"invalid binary CID at byte {offset}: {exc}") from exc
        end = digest_at + size
        if end > len(data):
            raise CIDError(
                f"invalid binary CID at byte {offset}: a {size}-byte digest, "
                f"{len(data) - digest_at} bytes left"
            )
        return cls(1, codec, bytes(data[pos:end])), end

    @classmethod
    def from_block(cls, data: bytes | memoryview, codec: int = RAW, version: int = 1) -> CID:
        """The sha2-256 CID of a block."""
        if version == 0 and codec != DAG_PB:
            raise CIDError("CIDv0 is always dag-pb")
        return cls(version, codec, b"\x12\x20" + hashlib.sha256(data).digest())

    @property
    def hash_code(self) -> int:
        return decode_varint(self.multihash)[0]

    @property
    def digest(self) -> bytes:
        _, pos = decode_varint(self.multihash)
        _, pos = decode_varint(self.multihash, pos)
        return self.multihash[pos:]

    @property
    def binary(self) -> bytes:
        """The binary form (what goes on chain and into CAR files)."""
        if self.version == 0:
            return self.multihash
        return encode_varint(1) + encode_varint(self.codec) + self.multihash

    def verify(self, data: bytes | memoryview) -> None:
        """Raise :class:`CIDError` unless ``data`` is the block this CID names."""
        code = self.hash_code
        if code == IDENTITY:
            matches = bytes(data) == self.digest
        else:
            matches = hashlib.sha256(data).digest() == self.digest
        if not matches:
            raise CIDError(f"block does not match CID {self}")

    def to_v1(self) -> CID:
        return CID(1, self.codec, self.multihash)

    def __str__(self) -> str:
        if self.version == 0:
            return b58encode(self.multihash)
        return "b" + base64.b32encode(self.binary).decode().lower().rstrip("=")

    def __repr__(self) -> str:
        return f"CID({self})"


def _check_multihash(code: int, size: int) -> None:
    if code == SHA2_256 and size != 32:
        raise CIDError(f"sha2-256 digest must be 32 bytes, not {size}")
    if code == IDENTITY and size > MAX_IDENTITY_DIGEST:
        raise CIDError(f"identity digest of {size} bytes exceeds {MAX_IDENTITY_DIGEST}")
    if code not in (SHA2_256, IDENTITY):
        raise CIDError(f"unsupported multihash 0x{code:x}: only sha2-256 and identity")


class Block(NamedTuple):
    """A block and the CID it is stored under; whoever made the pair checked it."""

    cid: CID
    data: bytes
