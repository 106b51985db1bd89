"""How the storage service's domain exceptions are answered: status, code and details."""

from __future__ import annotations

from robocloud.templates import RecordInvalid, TemplateIdInvalid, TemplateInvalid
from services.common.errors import ErrorMap, ErrorRule
from services.storage.bags import BagError
from services.storage.catalog import (
    CatalogFull,
    LifecycleConflict,
    NotAuthor,
    TemplateExists,
    TemplateImmutable,
    TemplateNotApproved,
    TemplateNotFound,
)
from services.storage.ingest import BagNotFetchable, JobNotFound, JobNotResumable, TooManyJobs
from services.storage.keywords import TooManyKeywordHits
from services.storage.matcher import BindingRefused
from services.storage.queries import QueryInvalid
from services.storage.recordstore import (
    OffloadFailed,
    RecordIdInvalid,
    RecordNotFound,
    RecordRejected,
)

# ----- templates, records and queries (engineer records) -----
RECORD_ERRORS = ErrorMap(
    {
        TemplateInvalid: ErrorRule(
            400,
            "invalid_template",
            lambda exc: {"problems": [problem.to_json() for problem in exc.problems]},
        ),
        TemplateIdInvalid: ErrorRule(
            400, "invalid_template_id", lambda exc: {"template": exc.text[:80]}
        ),
        TemplateNotFound: ErrorRule(
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
        CatalogFull: ErrorRule(507, "catalog_full", lambda exc: {"limit": exc.limit}),
        RecordInvalid: ErrorRule(400, "invalid_record", lambda exc: {"field": exc.path}),
        RecordRejected: ErrorRule(
            400,
            "invalid_record",
            lambda exc: {"index": exc.index, "field": exc.path, "reason": exc.code},
        ),
        OffloadFailed: ErrorRule(
            502, "cas_unavailable", lambda exc: {"index": exc.index, "field": exc.path}
        ),
        RecordIdInvalid: ErrorRule(400, "invalid_record_id", lambda exc: {"id": exc.text[:80]}),
        RecordNotFound: ErrorRule(404, "record_not_found", lambda exc: {"id": exc.record_id}),
        QueryInvalid: ErrorRule(
            400, "invalid_query", lambda exc: {"parameter": exc.parameter, "reason": exc.code}
        ),
        TooManyKeywordHits: ErrorRule(
            400, "query_too_broad", lambda exc: {"parameter": "keywords", "limit": exc.limit}
        ),
    }
)

# ----- bag ingestion and export (engineer bags) -----
INGEST_ERRORS = ErrorMap(
    {
        BagError: ErrorRule(
            400, "invalid_bag", lambda exc: {"file": exc.path.name, "offset": exc.offset}
        ),
        BagNotFetchable: ErrorRule(400, "invalid_bag", lambda exc: {"cid": exc.cid}),
        JobNotFound: ErrorRule(404, "job_not_found", lambda exc: {"job": exc.job_id[:64]}),
        JobNotResumable: ErrorRule(
            409, "job_not_resumable", lambda exc: {"job": exc.job_id, "status": exc.status}
        ),
        TooManyJobs: ErrorRule(
            429,
            "too_many_jobs",
            lambda exc: {"limit": exc.limit, "retry_after": 5},
            lambda _: {"Retry-After": "5"},
        ),
        BindingRefused: ErrorRule(400, "invalid_binding", lambda exc: {"field": exc.field}),
    }
)

ERRORS = RECORD_ERRORS | INGEST_ERRORS
