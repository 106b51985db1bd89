"""What each robot has ingested from each bag: a bag sent again adds no record twice.

A robot whose ingest answer was lost (a broken connection, a proxy's 502), or whose script
runs again, sends the same bag again. Its records are appended to logs that are anchored and
never rolled back, so a second job of the same bag used to store every record a second time,
and publish and advertise the dataset again. The node now remembers, for each robot and bag,
which topics went into which template and by which job; a later job of that robot and bag
skips those topics and reports the job that ingested them. A topic bound since, or bound
to another template (a new version), is ingested: that is new data.

A bag that is one file is named by its bytes, ``sha256:<hex>``, however it came (uploaded, or
by the CID of any import of it): when an upload was ``upload:<sha256>`` and a bag in cas
``cid:<cid>``, the same file sent once each way was two bags and its records were stored
twice. A ROS 2 bag directory, which only comes by CID, is ``cid:<cid>``. The table outlives
the jobs (a node keeps the last thousand): one row a topic of an ingested bag, in SQLite,
read one bag at a time.
"""

from __future__ import annotations

import sqlite3
import threading
from collections.abc import Iterable
from pathlib import Path

IngestedTopic = tuple[str, str, str]
"""(topic, message type, template id): what one topic of a bag became."""
IngestedRow = tuple[str, str, IngestedTopic, str]
"""(signer, bag, topic, job): a topic of a robot's bag and the job that committed it."""

_SCHEMA = """
CREATE TABLE IF NOT EXISTS ingested (
    signer TEXT NOT NULL,
    bag TEXT NOT NULL,
    topic TEXT NOT NULL,
    msgtype TEXT NOT NULL,
    template TEXT NOT NULL,
    job TEXT NOT NULL,
    PRIMARY KEY (signer, bag, topic, msgtype, template)
) WITHOUT ROWID
"""


class IngestedBags:
    """The topics each robot's bags gave to templates, and the job that committed them."""

    def __init__(self, path: Path) -> None:
        self.created = not path.exists()
        """Whether the table is new here: a node that ingested before it was kept fills
        it from the jobs it still has."""
        self._connection = sqlite3.connect(path, check_same_thread=False)
        self._connection.execute("PRAGMA synchronous = FULL")
        self._connection.execute(_SCHEMA)
        self._name_uploads_by_content()
        self._lock = threading.Lock()

    def _name_uploads_by_content(self) -> None:
        """Rename the rows of a table an older node kept, once: an upload's ``upload:<hex>``
        is the ``sha256:<hex>`` of its bytes (``user_version`` 1 says it is done)."""
        (version,) = self._connection.execute("PRAGMA user_version").fetchone()
        if version >= 1:
            return
        with self._connection:
            self._connection.execute(
                "UPDATE ingested SET bag = 'sha256:' || substr(bag, 8) WHERE bag LIKE 'upload:%'"
            )
            self._connection.execute("PRAGMA user_version = 1")

    def close(self) -> None:
        with self._lock:
            self._connection.close()

    def ingested(self, signer: str, bag: str) -> dict[IngestedTopic, str]:
        """Each topic of ``bag`` that ``signer`` has ingested, with the job that did."""
        with self._lock:
            rows = self._connection.execute(
                "SELECT topic, msgtype, template, job FROM ingested WHERE signer = ? AND bag = ?",
                (signer.lower(), bag),
            ).fetchall()
        return {(topic, msgtype, template): job for topic, msgtype, template, job in rows}

    def add(self, rows: Iterable[IngestedRow]) -> None:
        """Remember topics jobs committed, durably, all or none. A topic already remembered
        keeps its first job: a job committing again after a restart adds its own twice."""
        with self._lock, self._connection:
            self._connection.executemany(
                "INSERT OR IGNORE INTO ingested VALUES (?, ?, ?, ?, ?, ?)",
                ((signer.lower(), bag, *topic, job) for signer, bag, topic, job in rows),
            )
