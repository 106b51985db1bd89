"""dag-json links: found wherever they nest and in document order, bytes and look-alikes
not taken for links, bad documents refused; and the DAG walk following them as kubo's
recursive pin and ``dag export`` do."""

from __future__ import annotations

import json

import pytest

from robocloud.cid import CID, DAG_JSON, DAG_PB, Block
from robocloud.dagjson import DagJsonError, links
from robocloud.unixfs import UnixfsError, walk_dag

ONE = CID.from_block(b"one")
TWO = CID.from_block(b"two", DAG_PB)


def json_block(document: object) -> Block:
    data = json.dumps(document, separators=(",", ":"), sort_keys=True).encode()
    return Block(CID.from_block(data, DAG_JSON), data)


def test_links_are_found_wherever_they_nest_in_document_order() -> None:
    document = {
        "a": [{"/": str(ONE)}, {"deeper": {"/": str(TWO)}}],
        "b": {"/": str(ONE)},
        "c": "not a link",
    }
    assert links(json_block(document).data) == [ONE, TWO, ONE]


@pytest.mark.parametrize(
    "document",
    [
        {"/": {"bytes": "aGVsbG8"}},
        {"/": str(ONE), "other": 1},
        {"/": 7},
        ["/", str(ONE)],
        str(ONE),
    ],
    ids=["bytes", "more-keys", "not-a-string", "list", "plain-string"],
)
def test_what_only_looks_like_a_link_is_not_one(document: object) -> None:
    assert links(json_block(document).data) == []


@pytest.mark.parametrize(
    ("data", "reason"),
    [
        (b'{"/": "bafy-not-a-cid"}', "a link that is not a CID"),
        (b'{"a": [1, 2', "not dag-json"),
        (b"[" * 65 + b"]" * 65, "nested deeper than 64 levels"),
    ],
    ids=["bad-cid", "truncated", "too-deep"],
)
def test_bad_documents_are_refused(data: bytes, reason: str) -> None:
    with pytest.raises(DagJsonError, match=reason):
        links(data)


def test_the_walk_follows_dag_json_links_and_names_a_bad_block() -> None:
    """dag-json blocks were leaves: a pin of one kept nothing under it, and the next
    collection took what it linked."""
    leaf = Block(ONE, b"one")
    root = json_block({"leaf": {"/": str(ONE)}})
    store = {root.cid: root.data, leaf.cid: leaf.data}
    assert [block.cid for block in walk_dag(root.cid, store.__getitem__)] == [root.cid, ONE]
    assert [block.cid for block in walk_dag(root.cid, store.__getitem__, "entity")] == [root.cid]
    broken = Block(CID.from_block(b"{", DAG_JSON), b"{")
    with pytest.raises(UnixfsError, match=f"{broken.cid} is not a dag-json block"):
        list(walk_dag(broken.cid, {broken.cid: broken.data}.__getitem__))
