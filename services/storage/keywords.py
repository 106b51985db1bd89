"""Keywords of records in a Whoosh index: each word of a record's strings -> its addresses.

A record's address is its template id and its index, its place in the template's log. Whoosh
analysis costs about 0.1 ms a document, more than the rest of an append, so the index is
brought up to date by a background thread past its mark (``marks.json``, replaced atomically
after each commit) rather than on the write path: a record is acknowledged once its log holds
it, and is found by keyword a moment later.

Robots repeat their strings (a frame id, an encoding, a state name), so one document stands for
every record of a batch with the same text: its ``records`` field lists their indexes as runs
(``0-1999`` for a constant frame id). A batch starts at the template's mark, so after a crash
between a commit and its mark the same batch is indexed again from the same start; its key
(template, start, digest of the text) replaces the documents of the first attempt, which the
new batch covers, since a log only grows. Replacing costs a key lookup a document, a fifth of
a commit's time, so only a batch that may repeat one is indexed that way: a template's first
batch since the index was opened, and one after an attempt that failed; the others start at a
mark this process moved past everything it committed, and are only added.

Whoosh never fsyncs. A mark names records as indexed, so the files of a commit are fsynced
before the mark moves past it: a mark ahead of a commit lost in a power cut would hide its
records from keyword search for good. A power cut within a commit can still leave Whoosh's files
torn (an empty TOC, a segment of zeros); the index is derived from the logs, so one that cannot
be read at start is removed and indexed again from the first record rather than stopping the
node.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import threading
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from whoosh import fields, index
from whoosh.analysis import StandardAnalyzer
from whoosh.filedb.filestore import FileStorage
from whoosh.query import And, Query, Term

from services.common.durable import atomic_write, fsync_dir

log = logging.getLogger(__name__)

MARKS = "marks.json"
TEXTS = 2
"""What a record's keyword text holds (``segments.keyword_text``), saved with the marks: an
index of other texts is indexed again from the logs. 2: the strings inside arrays too."""
MAX_TERMS = 16
MAX_HITS = 100_000
"""Records one keyword query may match before it must be narrowed (a document stands for at
least one, so the search never needs more documents than this either)."""
WRITER_POOL_MB = 16
"""Postings a Whoosh writer holds in memory before spilling them to disk. Whoosh's default,
128 MB, is reached when a commit merges large segments, so the node's memory grew with its
keyword index (to about 300 MiB over 1.2 million records; 200 MiB with this bound)."""


class TooManyKeywordHits(Exception):
    def __init__(self, limit: int) -> None:
        super().__init__(f"the keywords match more than {limit} records; narrow the query")
        self.limit = limit


class KeywordTextsChanged(Exception):
    """The index holds texts of another :data:`TEXTS`: its records are indexed again."""


class KeywordIndexLost(Exception):
    """The marks name documents the Whoosh index does not hold (its last commits lost)."""


def runs(indexes: list[int]) -> str:
    """Ascending record indexes as runs: ``3,5-9,12``."""
    parts: list[str] = []
    start = previous = indexes[0]
    for index_ in indexes[1:]:
        if index_ != previous + 1:
            parts.append(f"{start}-{previous}" if previous > start else str(start))
            start = index_
        previous = index_
    parts.append(f"{start}-{previous}" if previous > start else str(start))
    return ",".join(parts)


def parse_runs(text: str) -> list[range]:
    found = []
    for part in text.split(","):
        first, _, last = part.partition("-")
        found.append(range(int(first), int(last or first) + 1))
    return found


class KeywordIndex:
    """The Whoosh index under ``directory`` and how far each template's log is in it."""

    def __init__(self, directory: Path) -> None:
        directory.mkdir(parents=True, exist_ok=True)
        self.directory = directory
        self.analyzer = StandardAnalyzer(stoplist=None, minsize=1)
        schema = fields.Schema(
            key=fields.ID(unique=True),
            template=fields.ID(stored=True),
            records=fields.STORED,
            text=fields.TEXT(analyzer=self.analyzer),
        )
        self.storage = FileStorage(str(directory), supports_mmap=False)
        """Segments read as files, never mapped, each written as its own files rather than one
        compound file (``compound=False``). Whoosh's merges and its writer's key lookups close
        their segment readers while views of a mapped segment are still exported, so the map
        (and its descriptor) lived until the cyclic collector ran: hundreds of descriptors and
        merged-away segments kept on disk under a node's large heap. Plain files close when
        their reader does; read through one compound file they cost a seek a read, separate
        files do not (searches 2.5x faster than mapped, commits within 10%)."""
        self._synced: set[str] = set()
        """Files of the index fsynced since it was opened: a killed process may have left
        the others in the page cache only."""
        try:
            self.index, self.marks = self._open(schema)
        except KeywordTextsChanged as changed:
            log.info("%s; indexing the logs again", changed)
            self._remove()
            self.index, self.marks = self.storage.create_index(schema), {}
        except Exception:
            log.warning(
                "the keyword index under %s cannot be read; indexing the logs again",
                directory,
                exc_info=True,
            )
            self._remove()
            self.index, self.marks = self.storage.create_index(schema), {}
        self._lock = threading.Lock()
        self._segments = threading.Lock()
        """Held by a search while its searcher reads, and by a commit: a commit removes the
        files of the segments it merged away, and a searcher opens a segment's files only
        when a hit first needs them, so a search racing a merge read a file that was gone
        (a 500, seen after a restart while the indexer caught up)."""
        self._marked_here: set[str] = set()
        """Templates whose every batch since the index was opened was committed and marked:
        no document holds the keys of a batch starting at their mark."""

    def _open(self, schema: fields.Schema) -> tuple[index.Index, dict[str, int]]:
        """The index and its marks, checked enough to trust the marks: a torn TOC or segment
        raises almost anything (unpickling, ``struct``, ``ord()`` of an empty read), and an
        index without the documents its marks name would hide their records for good."""
        path = self.directory / MARKS
        saved: dict[str, Any] = (
            json.loads(path.read_bytes()) if path.exists() else {"texts": TEXTS, "marks": {}}
        )
        if saved.get("texts") != TEXTS:
            raise KeywordTextsChanged(
                f"the keyword index under {self.directory} holds texts of version"
                f" {saved.get('texts', 1)}, not {TEXTS}"
            )
        marks: dict[str, int] = saved["marks"]
        if not self.storage.index_exists():
            if marks:
                raise KeywordIndexLost(f"{path} names records of a Whoosh index not there")
            return self.storage.create_index(schema), marks
        opened = self.storage.open_index()
        with opened.reader() as reader:
            lost = [
                name
                for name, mark in marks.items()
                if mark and not reader.doc_frequency("template", name)
            ]
        if lost:
            raise KeywordIndexLost(f"{path} names records of {lost} the Whoosh index lacks")
        return opened, marks

    def _remove(self) -> None:
        """Remove the index, its marks first and durably: marks left beside a fresh index
        would say records are indexed that are not."""
        (self.directory / MARKS).unlink(missing_ok=True)
        fsync_dir(self.directory)
        shutil.rmtree(self.directory)
        self.directory.mkdir()

    def mark(self, template_id: str) -> int:
        with self._lock:
            return self.marks.get(template_id, 0)

    def add(self, template_id: str, start: int, texts: Iterable[str], upto: int) -> None:
        """Index the texts of records ``start``, ``start + 1``... of ``template_id``, one
        document per distinct text; its mark becomes ``upto``."""
        grouped: dict[str, list[int]] = {}
        for index_, text in enumerate(texts, start):
            grouped.setdefault(text, []).append(index_)
        fresh = template_id in self._marked_here and start == self.mark(template_id)
        self._marked_here.discard(template_id)
        writer = self.index.writer(limitmb=WRITER_POOL_MB, compound=False)
        put = writer.add_document if fresh else writer.update_document
        try:
            for text, indexes in grouped.items():
                digest = hashlib.sha256(text.encode("utf-8", "surrogatepass")).hexdigest()[:32]
                put(
                    key=f"{template_id}/{start}/{digest}",
                    template=template_id,
                    records=runs(indexes),
                    text=text,
                )
        except BaseException:
            writer.cancel()
            raise
        with self._segments:
            writer.commit()
        self._sync()
        with self._lock:
            self.marks[template_id] = upto
            marks = dict(self.marks)
        atomic_write(self.directory / MARKS, json.dumps({"texts": TEXTS, "marks": marks}).encode())
        self._marked_here.add(template_id)

    def _sync(self) -> None:
        """Fsync what the last commit wrote and the directory naming it. Whoosh never writes a
        file twice (segments get random names, each commit a new TOC generation), so a file
        fsynced once is left alone: a commit costs the fsync of its own segment and TOC."""
        names = {
            entry.name
            for entry in os.scandir(self.directory)
            if entry.is_file() and entry.name != MARKS
        }
        for name in sorted(names - self._synced):
            fd = os.open(self.directory / name, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        fsync_dir(self.directory)
        self._synced = names

    def terms(self, text: str) -> list[str]:
        """The words of a query as the index analysed the records' text."""
        return [token.text for token in self.analyzer(text)][:MAX_TERMS]

    def search(self, words: list[str], template_id: str | None) -> dict[str, set[int]]:
        """Record indexes per template holding every word (and of ``template_id`` if given)."""
        clauses: list[Query] = [Term("text", word) for word in words]
        if template_id is not None:
            clauses.append(Term("template", template_id))
        found: dict[str, set[int]] = {}
        count = 0
        with self._segments, self.index.searcher() as searcher:
            for hit in searcher.search(And(clauses), limit=MAX_HITS + 1):
                spans = parse_runs(hit["records"])
                count += sum(len(span) for span in spans)
                if count > MAX_HITS:
                    raise TooManyKeywordHits(MAX_HITS)
                records = found.setdefault(hit["template"], set())
                for span in spans:
                    records.update(span)
        return found

    def close(self) -> None:
        self.index.close()
