"""How the storage service's domain exceptions are answered: status, code and details.

Each engineer's rules sit in their own block of ``ERRORS``, so that additions merge cleanly.
"""

from __future__ import annotations

from robocloud.proofs import RecordIdError
from robocloud.templates import RecordInvalid, TemplateIdInvalid, TemplateInvalid
from services.common.errors import ErrorMap, ErrorRule
from services.storage.anchoring import (
    EpochNotFound,
    InvalidConsistencyRange,
    NotAnchored,
    RecordNotFound,
    TemplateNotFound,
)
from services.storage.bags import BagError
from services.storage.casbags import BagCasUnavailable, BagNotFetchable, BagNotFound, BagTooLarge
from services.storage.catalog import (
    CatalogFull,
    LifecycleConflict,
    NotAuthor,
    TemplateExists,
    TemplateImmutable,
    TemplateNotApproved,
)
from services.storage.catalog import TemplateNotFound as CatalogTemplateNotFound
from services.storage.ingest import BagAwaitsResume, JobNotFound, JobNotResumable, TooManyJobs
from services.storage.keywords import TooManyKeywordHits
from services.storage.knowledge import (
    CasUnavailable,
    CidNotCanonical,
    DescriptionInvalid,
    DescriptionNotFound,
    DescriptionTooLarge,
    DescriptionUnparsable,
    InvalidTypeParameter,
    KnowledgeBaseFull,
    NotADescription,
    ShareExhausted,
)
from services.storage.matcher import BindingRefused
from services.storage.queries import QueryInvalid
from services.storage.recordlog import InvalidTemplateId
from services.storage.recordstore import (
    OffloadFailed,
    RecordRejected,
)
from services.storage.recordstore import RecordNotFound as StoredRecordNotFound
from services.storage.sparql import (
    NotAcceptableError,
    QueryFailedError,
    QueryRefusedError,
    QuerySyntaxError,
    QueryTimeoutError,
    QueryTooLargeError,
    ResultTooLargeError,
    UpdateRejectedError,
    WorkerFailedError,
    WorkersUnavailableError,
)

ERRORS = ErrorMap(
    {
        # ----- record logs, epochs and proofs (engineer anchor) -----
        RecordIdError: ErrorRule(
            400, "invalid_record_id", lambda exc: {"field": "id", "id": exc.text[:200]}
        ),
        InvalidTemplateId: ErrorRule(
            400,
            "invalid_template_id",
            lambda exc: {"field": "id", "template": exc.template_id[:200]},
        ),
        InvalidConsistencyRange: ErrorRule(
            400,
            "invalid_parameter",
            lambda exc: {"field": exc.field, "value": exc.value},
        ),
        RecordNotFound: ErrorRule(404, "record_not_found", lambda exc: {"id": str(exc.record_id)}),
        TemplateNotFound: ErrorRule(
            404, "template_not_found", lambda exc: {"template": exc.template}
        ),
        EpochNotFound: ErrorRule(404, "epoch_not_found", lambda exc: {"epoch": exc.epoch}),
        NotAnchored: ErrorRule(
            409,
            "not_anchored",
            lambda exc: {"id": str(exc.record_id), "epoch": exc.epoch},
        ),
        # ----- templates, records and queries (engineer records) -----
        TemplateInvalid: ErrorRule(
            400,
            "invalid_template",
            lambda exc: {"problems": [problem.to_json() for problem in exc.problems]},
        ),
        TemplateIdInvalid: ErrorRule(
            400, "invalid_template_id", lambda exc: {"template": exc.text[:80]}
        ),
        CatalogTemplateNotFound: ErrorRule(
            404, "template_not_found", lambda exc: {"template": exc.template_id}
        ),
        TemplateExists: ErrorRule(409, "template_exists", lambda exc: {"name": exc.name}),
        TemplateImmutable: ErrorRule(
            409,
            "template_immutable",
            lambda exc: {"template": exc.template_id, "status": exc.status},
        ),
        LifecycleConflict: ErrorRule(
            409,
            "invalid_transition",
            lambda exc: {"template": exc.template_id, "status": exc.status},
        ),
        NotAuthor: ErrorRule(
            403,
            "not_author",
            lambda exc: {"template": exc.template_id, "address": exc.address},
        ),
        TemplateNotApproved: ErrorRule(
            400,
            "template_not_approved",
            lambda exc: {"template": exc.template_id, "status": exc.status},
        ),
        CatalogFull: ErrorRule(
            507, "catalog_full", lambda exc: {"limit": exc.limit, "unit": exc.unit}
        ),
        RecordInvalid: ErrorRule(400, "invalid_record", lambda exc: {"field": exc.path}),
        RecordRejected: ErrorRule(
            400,
            "invalid_record",
            lambda exc: {"index": exc.index, "field": exc.path, "reason": exc.code},
        ),
        OffloadFailed: ErrorRule(
            502, "cas_unavailable", lambda exc: {"index": exc.index, "field": exc.path}
        ),
        StoredRecordNotFound: ErrorRule(404, "record_not_found", lambda exc: {"id": exc.record_id}),
        QueryInvalid: ErrorRule(
            400, "invalid_query", lambda exc: {"parameter": exc.parameter, "reason": exc.code}
        ),
        TooManyKeywordHits: ErrorRule(
            400, "query_too_broad", lambda exc: {"parameter": "keywords", "limit": exc.limit}
        ),
        # ----- bag ingestion and export (engineer bags) -----
        BagError: ErrorRule(
            400,
            "invalid_bag",
            lambda exc: {"file": None, "offset": exc.offset},
            message=lambda exc: exc.shown(exc.path),
        ),
        BagNotFetchable: ErrorRule(
            400,
            "invalid_bag",
            lambda exc: (
                {"cid": exc.cid, "reason": exc.reason}
                | ({"entry": exc.entry} if exc.entry is not None else {})
            ),
        ),
        BagNotFound: ErrorRule(404, "bag_not_found", lambda exc: {"cid": exc.cid}),
        BagTooLarge: ErrorRule(
            413, "payload_too_large", lambda exc: {"cid": exc.cid, "limit": exc.limit}
        ),
        BagCasUnavailable: ErrorRule(502, "cas_unavailable", lambda exc: {"cid": exc.cid}),
        JobNotFound: ErrorRule(404, "job_not_found", lambda exc: {"job": exc.job_id[:64]}),
        JobNotResumable: ErrorRule(
            409, "job_not_resumable", lambda exc: {"job": exc.job_id, "status": exc.status}
        ),
        BagAwaitsResume: ErrorRule(
            409, "job_resumable", lambda exc: {"job": exc.job_id, "bag": exc.bag}
        ),
        TooManyJobs: ErrorRule(
            429,
            "too_many_jobs",
            lambda exc: {"limit": exc.limit, "per": exc.per, "retry_after": 5},
            lambda _: {"Retry-After": "5"},
        ),
        BindingRefused: ErrorRule(400, "invalid_binding", lambda exc: {"field": exc.field}),
        # ----- knowledge base (engineer semantic) -----
        DescriptionInvalid: ErrorRule(
            400,
            "description_invalid",
            lambda exc: {"cid": exc.cid, "violations": exc.violations},
        ),
        DescriptionUnparsable: ErrorRule(
            400, "rdf_unparsable", lambda exc: {"cid": exc.cid, "line": exc.line}
        ),
        NotADescription: ErrorRule(400, "not_a_description", lambda exc: {"cid": exc.cid}),
        CidNotCanonical: ErrorRule(
            400, "cid_not_canonical", lambda exc: {"cid": exc.cid[:200], "expected": exc.expected}
        ),
        DescriptionTooLarge: ErrorRule(
            400, "description_too_large", lambda exc: {"cid": exc.cid, "limit": exc.limit}
        ),
        DescriptionNotFound: ErrorRule(404, "description_not_found", lambda exc: {"cid": exc.cid}),
        KnowledgeBaseFull: ErrorRule(
            507,
            "knowledge_base_full",
            lambda exc: {"cid": exc.cid, "size": exc.size, "used": exc.used, "limit": exc.limit},
        ),
        ShareExhausted: ErrorRule(
            507,
            "quota_exceeded",
            lambda exc: {
                "cid": exc.cid,
                "robot": exc.robot,
                "size": exc.size,
                "used": exc.used,
                "limit": exc.limit,
            },
        ),
        CasUnavailable: ErrorRule(502, "cas_unavailable", lambda exc: {"cid": exc.cid}),
        InvalidTypeParameter: ErrorRule(
            400, "invalid_parameter", lambda exc: {"field": exc.field, "value": exc.value[:200]}
        ),
        QuerySyntaxError: ErrorRule(400, "sparql_syntax"),
        UpdateRejectedError: ErrorRule(400, "sparql_update_rejected"),
        QueryFailedError: ErrorRule(400, "sparql_query_failed"),
        QueryRefusedError: ErrorRule(400, "sparql_query_refused"),
        QueryTooLargeError: ErrorRule(
            413, "query_too_large", lambda exc: {"size": exc.size, "limit": exc.limit}
        ),
        ResultTooLargeError: ErrorRule(400, "result_too_large", lambda exc: {"limit": exc.limit}),
        NotAcceptableError: ErrorRule(
            406,
            "not_acceptable",
            lambda exc: {
                "header": "Accept",
                "accept": exc.accept[:200],
                "available": exc.available,
            },
        ),
        QueryTimeoutError: ErrorRule(
            503,
            "query_timeout",
            lambda exc: {"timeout_s": exc.timeout_s},
            headers=lambda _: {"Retry-After": "1"},
        ),
        WorkerFailedError: ErrorRule(503, "query_worker_failed"),
        WorkersUnavailableError: ErrorRule(
            503, "knowledge_loading", headers=lambda _: {"Retry-After": "1"}
        ),
    }
)
