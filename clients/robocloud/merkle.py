"""Merkle tree hashes and proofs of RFC 6962 / RFC 9162 (Certificate Transparency logs).

Every record robocloud stores is a leaf of an append-only log of this shape; a robot checks
that a record is in a log (an inclusion proof) and that a log only grew (a consistency
proof) with nothing but SHA-256. Generation and verification follow RFC 9162 section 2.1
step by step, iteratively.

Generation takes ``subtree(start, end)``, the hash of the leaves ``[start, end)``, so that a
log which keeps the hashes of its complete subtrees answers in O(log n) reads; a plain list
of leaf hashes works too (:class:`MerkleTree`, for small logs and tests).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Sequence

from robocloud.errors import RobocloudError

HASH_SIZE = 32
EMPTY_ROOT = hashlib.sha256(b"").digest()

Subtree = Callable[[int, int], bytes]
"""The Merkle tree hash of the leaves ``[start, end)`` of one log."""


class ProofError(RobocloudError):
    """A proof that does not verify, or arguments no proof can exist for."""


def leaf_hash(data: bytes) -> bytes:
    return hashlib.sha256(b"\x00" + data).digest()


def node_hash(left: bytes, right: bytes) -> bytes:
    return hashlib.sha256(b"\x01" + left + right).digest()


def root(leaf_hashes: Sequence[bytes]) -> bytes:
    """MTH of the leaves: perfect subtrees from the left, folded from the right."""
    if not leaf_hashes:
        return EMPTY_ROOT
    stack: list[tuple[int, bytes]] = []
    for value in leaf_hashes:
        size = 1
        while stack and stack[-1][0] == size:
            left_size, left = stack.pop()
            size, value = left_size + size, node_hash(left, value)
        stack.append((size, value))
    value = stack.pop()[1]
    while stack:
        value = node_hash(stack.pop()[1], value)
    return value


def _split(size: int) -> int:
    """The largest power of two smaller than ``size`` (size > 1): where MTH splits."""
    return 1 << ((size - 1).bit_length() - 1)


def inclusion_proof(index: int, size: int, subtree: Subtree) -> list[bytes]:
    """PATH(index, D[size]) of RFC 6962 section 2.1.1, deepest sibling first."""
    if not 0 <= index < size:
        raise ProofError(f"leaf {index} is not in a tree of {size} leaves")
    path: list[bytes] = []
    start, end = 0, size
    while end - start > 1:
        middle = start + _split(end - start)
        if index < middle:
            path.append(subtree(middle, end))
            end = middle
        else:
            path.append(subtree(start, middle))
            start = middle
    return path[::-1]


def consistency_proof(first: int, second: int, subtree: Subtree) -> list[bytes]:
    """PROOF(first, D[second]) of RFC 6962 section 2.1.2; empty when ``first`` is 0 or equal."""
    if not 0 <= first <= second:
        raise ProofError(f"no consistency proof from {first} to {second} leaves")
    if first in (0, second):
        return []
    proof: list[bytes] = []
    start, end, known = 0, second, True
    remaining = first
    while remaining != end - start:
        middle = _split(end - start)
        if remaining <= middle:
            proof.append(subtree(start + middle, end))
            end = start + middle
        else:
            proof.append(subtree(start, start + middle))
            start, remaining, known = start + middle, remaining - middle, False
    if not known:
        proof.append(subtree(start, end))
    return proof[::-1]


def _check_hash(value: bytes, what: str) -> None:
    if len(value) != HASH_SIZE:
        raise ProofError(f"{what} has {len(value)} bytes, not {HASH_SIZE}")


def root_from_inclusion_proof(index: int, size: int, leaf: bytes, proof: Sequence[bytes]) -> bytes:
    """The root that ``proof`` leads to from ``leaf`` (RFC 9162 section 2.1.3.2)."""
    if not 0 <= index < size:
        raise ProofError(f"leaf {index} is not in a tree of {size} leaves")
    _check_hash(leaf, "the leaf hash")
    fn, sn, value = index, size - 1, leaf
    for position, sibling in enumerate(proof):
        _check_hash(sibling, f"proof[{position}]")
        if sn == 0:
            raise ProofError(f"the proof is longer than a tree of {size} leaves needs")
        if fn & 1 or fn == sn:
            value = node_hash(sibling, value)
            while not fn & 1 and fn:
                fn, sn = fn >> 1, sn >> 1
        else:
            value = node_hash(value, sibling)
        fn, sn = fn >> 1, sn >> 1
    if sn != 0:
        raise ProofError(f"the proof is shorter than a tree of {size} leaves needs")
    return value


def verify_inclusion(
    index: int, size: int, leaf: bytes, proof: Sequence[bytes], expected_root: bytes
) -> None:
    """Raise :class:`ProofError` unless ``leaf`` is leaf ``index`` of the tree ``root``."""
    _check_hash(expected_root, "the root")
    if root_from_inclusion_proof(index, size, leaf, proof) != expected_root:
        raise ProofError(f"the inclusion proof of leaf {index} leads to another root")


def verify_consistency(
    first: int, second: int, first_root: bytes, second_root: bytes, proof: Sequence[bytes]
) -> None:
    """Raise :class:`ProofError` unless the tree ``second_root`` extends ``first_root``.

    RFC 9162 section 2.1.4.2; a tree of 0 leaves is extended by every tree, with an empty
    proof, and a tree is consistent with itself only when both roots are the same.
    """
    _check_hash(first_root, "the first root")
    _check_hash(second_root, "the second root")
    for position, node in enumerate(proof):
        _check_hash(node, f"proof[{position}]")
    if not 0 <= first <= second:
        raise ProofError(f"a tree of {second} leaves cannot extend one of {first}")
    if first == 0 or first == second:
        if proof:
            raise ProofError("a proof from an empty or equal tree must be empty")
        if first == second and first_root != second_root:
            raise ProofError(f"two different roots for the same {first} leaves")
        return
    if not proof:
        raise ProofError("an empty proof cannot show that a tree grew")
    nodes = list(proof)
    if first & (first - 1) == 0:
        nodes.insert(0, first_root)
    fn, sn = first - 1, second - 1
    while fn & 1:
        fn, sn = fn >> 1, sn >> 1
    first_value = second_value = nodes[0]
    for node in nodes[1:]:
        if sn == 0:
            raise ProofError("the consistency proof is longer than the trees need")
        if fn & 1 or fn == sn:
            first_value = node_hash(node, first_value)
            second_value = node_hash(node, second_value)
            while not fn & 1 and fn:
                fn, sn = fn >> 1, sn >> 1
        else:
            second_value = node_hash(second_value, node)
        fn, sn = fn >> 1, sn >> 1
    if sn != 0 or first_value != first_root or second_value != second_root:
        raise ProofError(f"the consistency proof from {first} to {second} leaves does not hold")


class MerkleTree:
    """An in-memory log of leaf hashes, for small logs and tests (O(n) per subtree)."""

    def __init__(self, leaf_hashes: Sequence[bytes] = ()) -> None:
        self.leaves = list(leaf_hashes)

    def append(self, data: bytes) -> int:
        """Add a leaf of ``data``; its index."""
        self.leaves.append(leaf_hash(data))
        return len(self.leaves) - 1

    def subtree(self, start: int, end: int) -> bytes:
        return root(self.leaves[start:end])

    def root(self, size: int | None = None) -> bytes:
        return root(self.leaves[: len(self.leaves) if size is None else size])

    def inclusion_proof(self, index: int, size: int | None = None) -> list[bytes]:
        return inclusion_proof(index, len(self.leaves) if size is None else size, self.subtree)

    def consistency_proof(self, first: int, second: int | None = None) -> list[bytes]:
        return consistency_proof(
            first, len(self.leaves) if second is None else second, self.subtree
        )
