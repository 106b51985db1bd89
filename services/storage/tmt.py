"""The Template Merkle Tree: one RFC 6962 tree over the heads of every template log.

An epoch's heads (template id, size, root), sorted by template id, are the TMT's leaves, each
the JCS bytes of ``{"template", "size", "root"}``. Anchoring the TMT root commits the node to
every template log at once with one transaction, whatever the number of templates; a robot
checks a record with two inclusion proofs (record in template log, template head in TMT).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any

from robocloud import jcs, merkle


@dataclass(frozen=True, order=True)
class TemplateHead:
    template: str
    size: int
    root: bytes

    def leaf(self) -> bytes:
        """The TMT leaf's data: what a verifier recomputes from the proof's fields."""
        return tmt_leaf(self.template, self.size, self.root)

    def describe(self) -> dict[str, Any]:
        return {"template": self.template, "size": self.size, "root": self.root.hex()}


def tmt_leaf(template: str, size: int, root: bytes) -> bytes:
    return jcs.canonical({"template": template, "size": size, "root": root.hex()})


@dataclass(frozen=True)
class EpochTree:
    """The TMT of one epoch: its heads in template order and the proofs over them."""

    epoch: int
    heads: tuple[TemplateHead, ...]

    @classmethod
    def build(cls, epoch: int, heads: Iterable[TemplateHead]) -> EpochTree:
        ordered = tuple(sorted(heads))
        templates = [head.template for head in ordered]
        if len(set(templates)) != len(templates):
            raise ValueError(f"epoch {epoch} names a template twice")
        return cls(epoch, ordered)

    @cached_property
    def _tree(self) -> merkle.MerkleTree:
        return merkle.MerkleTree([merkle.leaf_hash(head.leaf()) for head in self.heads])

    @cached_property
    def _positions(self) -> Mapping[str, int]:
        return {head.template: position for position, head in enumerate(self.heads)}

    @property
    def root(self) -> bytes:
        return self._tree.root()

    @property
    def record_count(self) -> int:
        return sum(head.size for head in self.heads)

    def head(self, template: str) -> TemplateHead | None:
        position = self._positions.get(template)
        return None if position is None else self.heads[position]

    def inclusion(self, template: str) -> tuple[int, list[bytes]]:
        """The TMT leaf index of ``template``'s head and its inclusion proof."""
        position = self._positions[template]
        return position, self._tree.inclusion_proof(position)

    def manifest(self, node: str) -> dict[str, Any]:
        """The epoch's manifest as stored in cas and served at ``GET /v1/epochs/{epoch}``."""
        return {
            "epoch": self.epoch,
            "node": node,
            "heads": [head.describe() for head in self.heads],
            "record_count": self.record_count,
            "tmt_root": self.root.hex(),
        }


def heads_from(described: Sequence[Mapping[str, Any]]) -> list[TemplateHead]:
    """Heads back from their stored description (the node's own database: trusted)."""
    return [
        TemplateHead(str(head["template"]), int(head["size"]), bytes.fromhex(str(head["root"])))
        for head in described
    ]
