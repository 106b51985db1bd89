"""The knowledge base's pure parts: type parameters of application discovery, the ledger
follower's saved place (kept across restarts, started over when lost or unreadable), and what
each robot's descriptions take, read again at open."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.storage.knowledge import FollowState, InvalidTypeParameter, KnowledgeBase, type_iri

CID = "bafkreide5semuafsnds3ugrvm6fbwuyw2ijpj43gwjdxemstjkfozi37hq"


@pytest.mark.parametrize(
    ("value", "iri"),
    [
        ("image/jpeg", "https://www.iana.org/assignments/media-types/image/jpeg"),
        (
            "https://www.iana.org/assignments/media-types/application/vnd.apache.parquet",
            "https://www.iana.org/assignments/media-types/application/vnd.apache.parquet",
        ),
        (f"ipfs://{CID}", f"ipfs://{CID}"),
    ],
)
def test_a_type_is_a_media_type_its_iri_or_a_template(value: str, iri: str) -> None:
    assert type_iri(value, "consumes") == iri


@pytest.mark.parametrize(
    "value",
    ["jpeg", "image/jpeg> } ; DROP", "image/", "ipfs://not-a-cid", "ipfs://", "", "image/jp eg"],
)
def test_anything_else_is_refused_naming_the_field(value: str) -> None:
    with pytest.raises(InvalidTypeParameter) as caught:
        type_iri(value, "produces")
    assert (caught.value.field, caught.value.value) == ("produces", value)


def test_the_followers_place_survives_a_restart(tmp_path: Path) -> None:
    path = tmp_path / "follow.json"
    assert FollowState.load(path) == FollowState(0, -1, [], {})
    FollowState(12, 3, [CID], {"bafy": "not canonical"}).save(path)
    assert FollowState.load(path) == FollowState(12, 3, [CID], {"bafy": "not canonical"})


@pytest.mark.parametrize(
    "text", ["", "{", "[]", '{"block": "x"}', '{"block": 1, "log_index": 0, "pending": 5}']
)
def test_an_unreadable_place_starts_over_from_block_zero(tmp_path: Path, text: str) -> None:
    path = tmp_path / "follow.json"
    path.write_text(text)
    assert FollowState.load(path) == FollowState(0, -1, [], {})


def test_each_robots_bytes_are_read_again_from_the_files_it_owns(tmp_path: Path) -> None:
    """A line whose file is missing (a crash before the file was written) is dropped, and the
    later line of the add that stored the file wins; a torn last line is cut off."""
    descriptions = tmp_path / "descriptions"
    descriptions.mkdir()
    held = {"bafkreia": b"<a> <b> <c> .\n", "bafkreib": b"<a> <b> <d> .\n" * 3}
    for cid, data in held.items():
        (descriptions / f"{cid}.nt").write_bytes(data)
    (descriptions / "bafkreic.nt").write_bytes(b"<x> <y> <z> .\n")  # the node's own: no owner
    lines = ["bafkreia 0xaa", "bafkreilost 0xaa", "bafkreib 0xbb", "bafkreib 0xcc", "bafkreic"]
    (tmp_path / "owners.log").write_text("\n".join(lines[:-1]) + "\n" + lines[-1])
    knowledge = KnowledgeBase(tmp_path, workers=None, connect_cas=None)  # type: ignore[arg-type]
    try:
        assert knowledge.robot_bytes("0xAA") == len(held["bafkreia"])
        assert knowledge.robot_bytes("0xbb") == 0
        assert knowledge.robot_bytes("0xcc") == len(held["bafkreib"])
        assert knowledge.total_bytes == sum(map(len, held.values())) + 14
    finally:
        knowledge.close()
    assert (tmp_path / "owners.log").read_text() == "\n".join(lines[:4]) + "\n"
