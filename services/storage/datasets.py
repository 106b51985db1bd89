"""The dataset description of every ingested bag, stored, indexed and advertised on the ledger.

So that a robot that never saw the bag finds it by SPARQL (which robot, which topics and
templates, which time range, how many records) and fetches it: the bag itself goes to cas when
it was uploaded, each template's canonical JSON too (descriptions name templates by CID), the
description is validated and indexed by the knowledge base, and ``Registry.advertise(bag,
description)`` announces it, signed by the storage node's own key.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from robocloud import jcs
from robocloud.cas import Cas
from robocloud.cid import CID, parse_cid
from robocloud.ledger import Advertised, Ledger, SignedTransaction
from robocloud.proofs import RecordId
from robocloud.semantic import (
    Ingestion,
    SemanticError,
    TemplateCount,
    check_bounds,
    dataset_description,
    robot_iri,
)
from robocloud.templates import record_topic
from services.storage.anchoring import EpochStore
from services.storage.identity import NodeIdentity
from services.storage.ingest import DatasetUnpublishable, Job
from services.storage.knowledge import DescriptionRefused, KnowledgeBase, KnowledgeBaseFull
from services.storage.recordstore import RecordStore

log = logging.getLogger("robocloud.storage.datasets")


class DatasetPublisher:
    """Called by the ingest worker once a job has committed its records."""

    def __init__(
        self,
        store: RecordStore,
        knowledge: KnowledgeBase,
        cas: Callable[[], Cas],
        ledger: Callable[[], AbstractContextManager[Ledger]],
        node: NodeIdentity,
        epochs: EpochStore | None = None,
        epoch_wait_s: float = 5.0,
    ) -> None:
        self.store = store
        self.epochs = epochs
        """Where the epoch proving the dataset's records is found; None when nothing anchors."""
        self.epoch_wait_s = epoch_wait_s
        self.knowledge = knowledge
        self.cas = cas
        self.ledger = ledger
        self.node = node

    def __call__(
        self, job: Job, bag: Path, save_advertise_tx: Callable[[dict[str, Any]], None]
    ) -> dict[str, Any]:
        """Publish ``job``'s dataset; what was published, for the job's report.

        The advertise transaction is handed to ``save_advertise_tx`` before it is sent, for a
        later attempt of the job to find it (``_advertised_before``).

        The node registers before its first write to cas, which takes writes only from
        registered robots (``ROBOCLOUD_AUTH=registered``, as under ``make up``)."""
        with self.ledger() as chain:
            self.node.ensure_registered(chain)
            bag_cid = self._bag_cid(job, bag)
            counts = [self._count(template, ids) for template, ids in job.record_ids.items()]
            start, end = self._time_range(job)
            epoch, tmt_root = self._epoch(job)
            chain_id = chain.chain_id
            ingestion = Ingestion(
                job.id,
                robot_iri(chain_id, self.node.address),
                start,
                end,
                counts,
                epoch=epoch,
                tmt_root=tmt_root,
            )
            try:
                description = dataset_description(
                    bag_cid,
                    producer=robot_iri(chain_id, str(job.author["signer"])),
                    ingestion=ingestion,
                    topics=sorted(
                        {record_topic(t.topic) for t in job.topics if t.template is not None}
                    ),
                    title=f"ROS bag {bag_cid}",
                )
                check_bounds(description)
            except SemanticError as exc:
                raise DatasetUnpublishable(f"the dataset cannot be described: {exc}") from exc
            description_cid = self.cas().add_bytes(description.canonical())
            self._index(description_cid, job)
            earlier = self._advertised_before(
                chain, job, bag_cid, description_cid, save_advertise_tx
            )
            if earlier is not None:
                return earlier
            event = chain.advertise(
                bag_cid.binary,
                description_cid.binary,
                before_send=lambda signed: save_advertise_tx(signed.to_json()),
            )
        log.info(
            "dataset advertised",
            extra={"job": job.id, "cid": str(bag_cid), "description": str(description_cid)},
        )
        return {"cid": str(bag_cid), "description": str(description_cid), "tx": event.tx_hash}

    def _index(self, description_cid: CID, job: Job) -> None:
        """Index the description here; a full knowledge base does not hold the dataset back.
        The advertisement is what other robots find it by, and this node's ledger follower
        keeps the description pending until there is room."""
        try:
            self.knowledge.add(str(description_cid))
        except DescriptionRefused as exc:
            raise DatasetUnpublishable(
                f"the knowledge base refuses the dataset's description: {exc}"
            ) from exc
        except KnowledgeBaseFull as exc:
            log.warning(
                "dataset description not indexed here: the knowledge base is full",
                extra={"job": job.id, "description": str(description_cid), "error": str(exc)},
            )

    def _advertised_before(
        self,
        chain: Ledger,
        job: Job,
        bag_cid: CID,
        description_cid: CID,
        save_advertise_tx: Callable[[dict[str, Any]], None],
    ) -> dict[str, Any] | None:
        """This node's advertisement of the bag with this job's description when an attempt of
        the job was cut short between ``Registry.advertise`` and the job saving what it
        published: not made twice.

        Only on a job's later attempt (``publish_attempts``), since on the first another
        job's advertisement of the same bag is no reason not to advertise this one. And only
        one of this description: the node's advertisement of another (an earlier job's of the
        same bag, whose records are in another epoch) was reported as this job's, whose own
        description was then never advertised.
        """
        if job.publish_attempts <= 1:
            return None
        sent = self._saved_advertise(chain, job, bag_cid, save_advertise_tx)
        mine = chain.advertisements(cid=bag_cid.binary, advertiser=self.node.address)
        if sent is not None:
            mine.append(sent)
        same = [
            event
            for event in mine
            if event.cid == bag_cid.binary and event.description_cid == description_cid.binary
        ]
        if not same:
            if mine:
                log.info(
                    "the bag was advertised with another description: advertising this one",
                    extra={"job": job.id, "cid": str(bag_cid), "description": str(description_cid)},
                )
            return None
        event = same[-1]
        log.info(
            "dataset advertised by an earlier attempt",
            extra={"job": job.id, "cid": str(bag_cid), "tx": event.tx_hash},
        )
        return {"cid": str(bag_cid), "description": str(description_cid), "tx": event.tx_hash}

    @staticmethod
    def _saved_advertise(
        chain: Ledger,
        job: Job,
        bag_cid: CID,
        save_advertise_tx: Callable[[dict[str, Any]], None],
    ) -> Advertised | None:
        """What the advertise transaction an earlier attempt saved advertised, once mined: it
        is sent again and waited for, since behind an external node it may still be pending
        (not found by ``eth_getLogs``), and replaced at a higher price (saved first) once it
        has waited past the receipt timeout. None when none was saved, or it reverted or its
        nonce went to another transaction, so it never advertised anything; the caller reads
        the node's advertisements after this, so one made by a transaction the replacement
        replaced is found there."""
        if job.advertise_tx is None:
            return None
        return chain.advertised_by(
            SignedTransaction.from_json(job.advertise_tx),
            bag_cid.binary,
            before_send=lambda signed: save_advertise_tx(signed.to_json()),
        )

    def _epoch(self, job: Job) -> tuple[int | None, str | None]:
        """The first epoch holding every record of the job, and its TMT root: cut within an
        epoch's length of the commit, so waited for that long (anchoring follows later)."""
        if self.epochs is None:
            return None, None
        last = [RecordId.parse(ids[-1]) for ids in job.record_ids.values()]
        deadline = time.monotonic() + self.epoch_wait_s
        while True:
            found = [self.epochs.epoch_of(record.template, record.index) for record in last]
            if all(epoch is not None for epoch in found):
                epoch = max(epoch for epoch in found if epoch is not None)
                tree = self.epochs.tree(epoch)
                return (epoch, tree.root.hex()) if tree is not None else (None, None)
            if time.monotonic() > deadline:
                return None, None
            time.sleep(0.1)

    def _bag_cid(self, job: Job, bag: Path) -> CID:
        """The CID the bag came by, else the CID of the uploaded file, put in cas."""
        kind, _, value = job.bag.partition(":")
        if kind == "cid":
            return parse_cid(value, "bag")
        return self.cas().add_directory(bag) if bag.is_dir() else self.cas().add_file(bag)

    def _count(self, template_id: str, ids: list[str]) -> TemplateCount:
        """A template's records in the job, named by the CID of its canonical JSON in cas."""
        document = self.store.catalog.approved(template_id).to_json()
        template_cid = self.cas().add_bytes(jcs.canonical(document))
        first, last = (RecordId.parse(text).index for text in ids)
        return TemplateCount(template_id, template_cid, last - first + 1)

    def _time_range(self, job: Job) -> tuple[datetime, datetime]:
        """From the first to the last record the job committed, over all its templates."""
        ids = [text for first_and_last in job.record_ids.values() for text in first_and_last]
        times = [self.store.get(text).record["t"] for text in ids]
        return _utc(min(times)), _utc(max(times))


def _utc(nanoseconds: int) -> datetime:
    return datetime.fromtimestamp(nanoseconds / 1e9, tz=UTC)
