"""Keywords of records in a Whoosh index: each word of a record's strings -> its address.

A record's address is ``<template id>/<index>``, its place in the template's log. Whoosh
analysis costs about 0.1 ms a record, more than the rest of an append, so the index is
brought up to date by a background thread that reads the logs past its mark (``marks.json``,
replaced atomically after each commit) rather than on the write path: a record is
acknowledged once its log holds it, and is found by keyword a moment later. Documents are
written with ``update_document`` on the unique address, so re-indexing what a crash left
between a commit and its mark never doubles an entry.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterable
from pathlib import Path

from whoosh import fields, index
from whoosh.analysis import StandardAnalyzer
from whoosh.query import And, Query, Term

from services.common.durable import atomic_write

MARKS = "marks.json"
MAX_TERMS = 16
MAX_HITS = 100_000
"""Addresses one keyword query may match before it must be narrowed."""
WRITER_POOL_MB = 16
"""Postings a Whoosh writer holds in memory before spilling them to disk. Whoosh's default,
128 MB, is reached when a commit merges large segments, so the node's memory grew with its
keyword index (to about 300 MiB over 1.2 million records; 200 MiB with this bound)."""


class TooManyKeywordHits(Exception):
    def __init__(self, limit: int) -> None:
        super().__init__(f"the keywords match more than {limit} records; narrow the query")
        self.limit = limit


def address(template_id: str, index_: int) -> str:
    return f"{template_id}/{index_}"


class KeywordIndex:
    """The Whoosh index under ``directory`` and how far each template's log is in it."""

    def __init__(self, directory: Path) -> None:
        directory.mkdir(parents=True, exist_ok=True)
        self.directory = directory
        self.analyzer = StandardAnalyzer(stoplist=None, minsize=1)
        schema = fields.Schema(
            address=fields.ID(stored=True, unique=True),
            template=fields.ID,
            text=fields.TEXT(analyzer=self.analyzer),
        )
        if index.exists_in(directory):
            self.index = index.open_dir(directory)
        else:
            self.index = index.create_in(directory, schema)
        marks = directory / MARKS
        self.marks: dict[str, int] = json.loads(marks.read_bytes()) if marks.exists() else {}
        self._lock = threading.Lock()

    def mark(self, template_id: str) -> int:
        with self._lock:
            return self.marks.get(template_id, 0)

    def add(self, template_id: str, texts: Iterable[tuple[int, str]], upto: int) -> None:
        """Index ``(record index, text)`` pairs of ``template_id``; its mark becomes ``upto``."""
        writer = self.index.writer(limitmb=WRITER_POOL_MB)
        try:
            for record_index, text in texts:
                writer.update_document(
                    address=address(template_id, record_index), template=template_id, text=text
                )
        except BaseException:
            writer.cancel()
            raise
        writer.commit()
        with self._lock:
            self.marks[template_id] = upto
            marks = dict(self.marks)
        atomic_write(self.directory / MARKS, json.dumps(marks).encode())

    def terms(self, text: str) -> list[str]:
        """The words of a query as the index analysed the records' text."""
        return [token.text for token in self.analyzer(text)][:MAX_TERMS]

    def search(self, words: list[str], template_id: str | None) -> dict[str, set[int]]:
        """Record indexes per template holding every word (and of ``template_id`` if given)."""
        clauses: list[Query] = [Term("text", word) for word in words]
        if template_id is not None:
            clauses.append(Term("template", template_id))
        found: dict[str, set[int]] = {}
        with self.index.searcher() as searcher:
            hits = searcher.search(And(clauses), limit=MAX_HITS + 1)
            if hits.scored_length() > MAX_HITS:
                raise TooManyKeywordHits(MAX_HITS)
            for hit in hits:
                template, _, position = hit["address"].rpartition("/")
                found.setdefault(template, set()).add(int(position))
        return found

    def close(self) -> None:
        self.index.close()
