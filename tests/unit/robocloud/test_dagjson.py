"""dag-json links: found wherever they nest and in document order, bytes and look-alikes
not taken for links, bad documents refused; and the DAG walk following them as kubo's
recursive pin and ``dag export`` do."""

from __future__ import annotations

import json
import random
from typing import Any

import pytest

from robocloud.cid import CID, DAG_JSON, DAG_PB, Block, CIDError, parse_cid
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
        (b"[" * 1025 + b"]" * 1025, "nested deeper than 1024 levels"),
        (b'{"/": ""}', "a link that is not a CID"),
        (b'{"a": 1, "a": 2}', "repeated map key 'a'"),
        (b'["\\ud800"]', "lone UTF-16 surrogate"),
        (b'["caf\xe9"]', "not UTF-8"),
        (b"[1] [2]", "data after the document"),
        (b"[01]", "expected ',' or the end of the list"),
        (b'{"a" 1}', "expected ':'"),
        (b"{1: 2}", "expected a map key"),
        (b"[NaN]", "expected a value"),
        (b"", "expected a value"),
        (b"[1e999]", "beyond the range of a 64-bit float at character 1"),
        (b"[-1.7976931348623159e308]", "beyond the range"),
        (b"[" + b"9" * 309 + b"]", "beyond the range"),
    ],
    ids=[
        "bad-cid",
        "truncated",
        "too-deep",
        "empty-cid",
        "repeated-key",
        "lone-surrogate",
        "latin-1",
        "trailing",
        "leading-zero",
        "no-colon",
        "number-key",
        "nan",
        "empty",
        "float-overflow",
        "past-max-float",
        "integer-overflow",
    ],
)
def test_bad_documents_are_refused(data: bytes, reason: str) -> None:
    with pytest.raises(DagJsonError, match=reason):
        links(data)


def test_numbers_a_64_bit_float_holds_are_taken() -> None:
    """Go's ``strconv.ParseFloat``, which reads go-ipld-prime's dag-json numbers, refuses only
    an overflow: an underflow is zero, and the largest float is a float."""
    data = b"[1e-999, 1.7976931348623157e308, -4.9e-324, " + b"9" * 308 + b', {"/": "%s"}]'
    assert links(data % str(ONE).encode()) == [ONE]


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


def test_nesting_is_taken_to_go_ipld_primes_depth() -> None:
    """go-ipld-prime (kubo's decoder) takes 1,024 levels; cas refused more than 64, the bound
    its JSON parser needed, so kubo's DAGs of 65 to 1,024 levels could not be pinned."""
    depth = 1024
    data = b'{"a":' * (depth - 1) + f'{{"/":"{ONE}"}}'.encode() + b"}" * (depth - 1)
    assert links(data) == [ONE]


def reference_links(data: bytes) -> list[CID] | str:
    """The links as a parse with ``json.loads`` and a walk of its values find them, or
    ``"refused"`` when one of them is not a CID."""
    found: list[CID] = []
    pending: list[Any] = [json.loads(data)]
    while pending:
        value = pending.pop()
        if isinstance(value, dict):
            if len(value) == 1 and isinstance(value.get("/"), str):
                try:
                    found.append(parse_cid(value["/"]))
                except CIDError:
                    return "refused"
                continue
            pending.extend(reversed(list(value.values())))
        elif isinstance(value, list):
            pending.extend(reversed(value))
    return found


def links_or_refused(data: bytes) -> list[CID] | str:
    try:
        return links(data)
    except DagJsonError as exc:
        return "refused" if "a link that is not a CID" in str(exc) else str(exc)


def random_document(rng: random.Random, depth: int = 0) -> Any:
    kind = rng.choice(["map", "list", "link", "scalar"] if depth < 6 else ["link", "scalar"])
    if kind == "map":
        keys = rng.sample(["a", "/", "b", "long key", "\u00e9", "bytes"], rng.randint(0, 4))
        return {key: random_document(rng, depth + 1) for key in keys}
    if kind == "list":
        return [random_document(rng, depth + 1) for _ in range(rng.randint(0, 4))]
    if kind == "link":
        return {"/": str(rng.choice([ONE, TWO]))}
    return rng.choice([0, -7, 1.5e-3, 10**30, "text", 'caf\u00e9 "quoted"', True, None])


def test_links_agree_with_a_json_parse_on_random_documents() -> None:
    rng = random.Random(20261126)
    for _ in range(500):
        document = random_document(rng)
        indent = rng.choice([None, 1, "\t"])
        data = json.dumps(document, indent=indent, ensure_ascii=rng.random() < 0.5).encode()
        assert links_or_refused(data) == reference_links(data), data
