"""RFC 6962 / RFC 9162 Merkle proofs against Certificate Transparency's published vectors.

The vectors (8 leaves, their roots, inclusion and consistency proofs) are those of
transparency-dev/merkle's proof/verify_test.go (Apache-2.0), the Go implementation behind
Certificate Transparency logs and Trillian; the corruptions mirror that file's probes.
"""

from __future__ import annotations

import hashlib
import itertools

import pytest

from robocloud.merkle import (
    EMPTY_ROOT,
    MerkleTree,
    ProofError,
    consistency_proof,
    inclusion_proof,
    leaf_hash,
    node_hash,
    root,
    root_from_inclusion_proof,
    verify_consistency,
    verify_inclusion,
)

LEAVES = [
    bytes.fromhex(h)
    for h in (
        *("", "00", "10", "2021", "3031", "40414243", "5051525354555657"),
        "606162636465666768696a6b6c6d6e6f",
    )
]
ROOTS = [
    bytes.fromhex(h)
    for h in (
        "6e340b9cffb37a989ca544e6bb780a2c78901d3fb33738768511a30617afa01d",
        "fac54203e7cc696cf0dfcb42c92a1d9dbaf70ad9e621f4bd8d98662f00e3c125",
        "aeb6bcfe274b70a14fb067a5e5578264db0fa9b51af5e0ba159158f329e06e77",
        "d37ee418976dd95753c1c73862b9398fa2a2cf9b4ff0fdfe8b30cd95209614b7",
        "4e3bbb1f7b478dcfe71fb631631519a3bca12c9aefca1612bfce4c13a86264d4",
        "76e67dadbcdf1e10e1b74ddc608abd2f98dfb16fbce75277b5232a127f2087ef",
        "ddb89be403809e325750d3d263cd78929c2942b7942a34b77e122c9594a74c8c",
        "5dc9da79a70659a9ad559cb701ded9a2ab9d823aad2f4960cfe370eff4604328",
    )
]


def hashes(*values: str) -> list[bytes]:
    return [bytes.fromhex(value) for value in values]


# (leaf number counted from 1, tree size, proof)
INCLUSION = [
    (1, 1, []),
    (
        1,
        8,
        hashes(
            "96a296d224f285c67bee93c30f8a309157f0daa35dc5b87e410b78630a09cfc7",
            "5f083f0a1a33ca076a95279832580db3e0ef4584bdff1f54c8a360f50de3031e",
            "6b47aaf29ee3c2af9af889bc1fb9254dabd31177f16232dd6aab035ca39bf6e4",
        ),
    ),
    (
        6,
        8,
        hashes(
            "bc1a0643b12e4d2d7c77918f44e0f4f79a838b6cf9ec5b5c283e1f4d88599e6b",
            "ca854ea128ed050b41b35ffc1b87b8eb2bde461e9e3b5596ece6b9d5975a0ae0",
            "d37ee418976dd95753c1c73862b9398fa2a2cf9b4ff0fdfe8b30cd95209614b7",
        ),
    ),
    (3, 3, hashes("fac54203e7cc696cf0dfcb42c92a1d9dbaf70ad9e621f4bd8d98662f00e3c125")),
    (
        2,
        5,
        hashes(
            "6e340b9cffb37a989ca544e6bb780a2c78901d3fb33738768511a30617afa01d",
            "5f083f0a1a33ca076a95279832580db3e0ef4584bdff1f54c8a360f50de3031e",
            "bc1a0643b12e4d2d7c77918f44e0f4f79a838b6cf9ec5b5c283e1f4d88599e6b",
        ),
    ),
]

CONSISTENCY = [
    (1, 1, []),
    (
        1,
        8,
        hashes(
            "96a296d224f285c67bee93c30f8a309157f0daa35dc5b87e410b78630a09cfc7",
            "5f083f0a1a33ca076a95279832580db3e0ef4584bdff1f54c8a360f50de3031e",
            "6b47aaf29ee3c2af9af889bc1fb9254dabd31177f16232dd6aab035ca39bf6e4",
        ),
    ),
    (
        6,
        8,
        hashes(
            "0ebc5d3437fbe2db158b9f126a1d118e308181031d0a949f8dededebc558ef6a",
            "ca854ea128ed050b41b35ffc1b87b8eb2bde461e9e3b5596ece6b9d5975a0ae0",
            "d37ee418976dd95753c1c73862b9398fa2a2cf9b4ff0fdfe8b30cd95209614b7",
        ),
    ),
    (
        2,
        5,
        hashes(
            "5f083f0a1a33ca076a95279832580db3e0ef4584bdff1f54c8a360f50de3031e",
            "bc1a0643b12e4d2d7c77918f44e0f4f79a838b6cf9ec5b5c283e1f4d88599e6b",
        ),
    ),
    (
        6,
        7,
        hashes(
            "0ebc5d3437fbe2db158b9f126a1d118e308181031d0a949f8dededebc558ef6a",
            "b08693ec2e721597130641e8211e7eedccb4c26413963eee6c1e2ed16ffb1a5f",
            "d37ee418976dd95753c1c73862b9398fa2a2cf9b4ff0fdfe8b30cd95209614b7",
        ),
    ),
]

TREE = MerkleTree([leaf_hash(data) for data in LEAVES])
SOME_HASH = bytes.fromhex("abacaba000000000000000000000000000000000000000000060061e00123456")


def test_hashes_are_domain_separated() -> None:
    assert leaf_hash(b"") == hashlib.sha256(b"\x00").digest()
    assert node_hash(b"a", b"b") == hashlib.sha256(b"\x01ab").digest()
    assert root([]) == EMPTY_ROOT == hashlib.sha256(b"").digest()


@pytest.mark.parametrize("size", range(1, 9))
def test_roots_of_every_prefix(size: int) -> None:
    assert TREE.root(size) == ROOTS[size - 1]


@pytest.mark.parametrize(("leaf", "size", "proof"), INCLUSION)
def test_inclusion_proofs_match_the_vectors_and_verify(
    leaf: int, size: int, proof: list[bytes]
) -> None:
    assert TREE.inclusion_proof(leaf - 1, size) == proof
    verify_inclusion(leaf - 1, size, TREE.leaves[leaf - 1], proof, ROOTS[size - 1])


@pytest.mark.parametrize(("first", "second", "proof"), CONSISTENCY)
def test_consistency_proofs_match_the_vectors_and_verify(
    first: int, second: int, proof: list[bytes]
) -> None:
    assert TREE.consistency_proof(first, second) == proof
    verify_consistency(first, second, ROOTS[first - 1], ROOTS[second - 1], proof)


def _flip(proof: list[bytes], position: int, bit: int) -> list[bytes]:
    changed = list(proof)
    changed[position] = bytes([changed[position][0] ^ bit]) + changed[position][1:]
    return changed


@pytest.mark.parametrize(("leaf", "size", "proof"), [v for v in INCLUSION if v[1] > 1])
def test_corrupted_inclusion_proofs_fail(leaf: int, size: int, proof: list[bytes]) -> None:
    index, good_root, good_leaf = leaf - 1, ROOTS[size - 1], TREE.leaves[leaf - 1]
    probes = [
        (index - 1, size, good_leaf, proof, good_root),
        (index + 1, size, good_leaf, proof, good_root),
        (index ^ 2, size, good_leaf, proof, good_root),
        (index, size * 2, good_leaf, proof, good_root),
        (index, size // 2, good_leaf, proof, good_root),
        (index, size, leaf_hash(b"WrongLeaf"), proof, good_root),
        (index, size, good_leaf, proof, EMPTY_ROOT),
        (index, size, good_leaf, proof, SOME_HASH),
        (index, size, good_leaf, [*proof, good_root], good_root),
        (index, size, good_leaf, [good_root, *proof], good_root),
        (index, size, good_leaf, proof[:-1], good_root),
        (index, size, good_leaf, [proof[0], SOME_HASH, *proof[1:]], good_root),
        *((index, size, good_leaf, _flip(proof, i, 8), good_root) for i in range(len(proof))),
    ]
    for probe in probes:
        with pytest.raises(ProofError):
            verify_inclusion(*probe)


@pytest.mark.parametrize(("first", "second", "proof"), [v for v in CONSISTENCY if v[2]])
def test_corrupted_consistency_proofs_fail(first: int, second: int, proof: list[bytes]) -> None:
    root1, root2 = ROOTS[first - 1], ROOTS[second - 1]
    probes = [
        (first - 1, second, root1, root2, proof),
        (first + 1, second, root1, root2, proof),
        (first ^ 2, second, root1, root2, proof),
        (first, second * 2, root1, root2, proof),
        (first, second // 2, root1, root2, proof),
        (first, second, SOME_HASH, root2, proof),
        (first, second, root1, SOME_HASH, proof),
        (first, second, root2, root1, proof),
        (first, second, root1, root2, []),
        (first, second, root1, root2, [*proof, root1]),
        (first, second, root1, root2, [*proof, root2]),
        (first, second, root1, root2, [root1, *proof]),
        (first, second, root1, root2, [root2, *proof]),
        (first, second, root1, root2, [proof[0], *proof]),
        (first, second, root1, root2, proof[:-1]),
        *((first, second, root1, root2, _flip(proof, i, 16)) for i in range(len(proof))),
    ]
    for probe in probes:
        with pytest.raises(ProofError):
            verify_consistency(*probe)


def test_every_proof_of_a_larger_tree_round_trips() -> None:
    tree = MerkleTree()
    for number in range(70):
        tree.append(number.to_bytes(4, "big"))
    for size in range(1, 71):
        for index in range(size):
            proof = tree.inclusion_proof(index, size)
            assert root_from_inclusion_proof(index, size, tree.leaves[index], proof) == tree.root(
                size
            )
    for first, second in itertools.combinations_with_replacement(range(71), 2):
        proof = tree.consistency_proof(first, second)
        verify_consistency(first, second, tree.root(first), tree.root(second), proof)


@pytest.mark.parametrize(
    ("index", "size"), [(0, 0), (1, 1), (5, 3), (-1, 4)], ids=["empty", "past", "beyond", "neg"]
)
def test_impossible_inclusion_arguments_are_proof_errors(index: int, size: int) -> None:
    with pytest.raises(ProofError):
        verify_inclusion(index, size, SOME_HASH, [], SOME_HASH)
    if size:
        with pytest.raises(ProofError):
            inclusion_proof(index, size, TREE.subtree)


def test_hashes_of_the_wrong_length_are_refused() -> None:
    with pytest.raises(ProofError, match="proof\\[0\\] has 31 bytes"):
        verify_inclusion(0, 2, SOME_HASH, [bytes(31)], SOME_HASH)
    with pytest.raises(ProofError, match="the root has 0 bytes"):
        verify_inclusion(0, 1, SOME_HASH, [], b"")


def test_a_consistency_proof_for_shrinking_is_refused() -> None:
    with pytest.raises(ProofError):
        consistency_proof(5, 3, TREE.subtree)


def test_trivial_consistency_cases() -> None:
    verify_consistency(0, 5, SOME_HASH, ROOTS[4], [])
    verify_consistency(3, 3, ROOTS[2], ROOTS[2], [])
    with pytest.raises(ProofError):
        verify_consistency(3, 3, ROOTS[2], ROOTS[3], [])
    with pytest.raises(ProofError):
        verify_consistency(2, 1, ROOTS[1], ROOTS[0], [])
    with pytest.raises(ProofError):
        verify_consistency(0, 1, EMPTY_ROOT, ROOTS[0], [EMPTY_ROOT])


def test_the_rfc_example_tree_of_7_leaves() -> None:
    """RFC 6962 section 2.1.3 (RFC 9162 section 2.1.5): its audit paths and consistency
    proofs, named by the nodes of its figure, for any 7 leaves d0..d6."""
    tree = MerkleTree()
    for index in range(7):
        tree.append(f"d{index}".encode())
    a, b, c, d, e, f, leaf6 = tree.leaves
    g, h, i = node_hash(a, b), node_hash(c, d), node_hash(e, f)
    j = leaf6
    k, l_node = node_hash(g, h), node_hash(i, j)
    assert tree.root() == node_hash(k, l_node)
    assert tree.inclusion_proof(0) == [b, h, l_node]
    assert tree.inclusion_proof(3) == [c, g, l_node]
    assert tree.inclusion_proof(4) == [f, j, k]
    assert tree.inclusion_proof(6) == [i, k]
    assert tree.root(3) == node_hash(g, c)
    assert tree.root(4) == k
    assert tree.root(6) == node_hash(k, i)
    assert tree.consistency_proof(3) == [c, d, g, l_node]
    assert tree.consistency_proof(4) == [l_node]
    assert tree.consistency_proof(6) == [i, j, k]
    for first in (3, 4, 6):
        verify_consistency(first, 7, tree.root(first), tree.root(), tree.consistency_proof(first))
    for index in (0, 3, 4, 6):
        verify_inclusion(index, 7, tree.leaves[index], tree.inclusion_proof(index), tree.root())
