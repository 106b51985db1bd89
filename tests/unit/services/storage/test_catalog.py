"""The template catalog: lifecycle, immutability of approved versions, persistence."""

from __future__ import annotations

import errno
from pathlib import Path
from typing import Any

import pytest

from robocloud.templates import TemplateIdInvalid, TemplateInvalid, parse_template
from services.common import durable
from services.storage.catalog import (
    Catalog,
    CatalogFull,
    LifecycleConflict,
    NotAuthor,
    TemplateExists,
    TemplateImmutable,
    TemplateNotApproved,
    TemplateNotFound,
)

AUTHOR = "0x90F8bf6A479f320ead074411a4B0e7944Ea8c9C1"
OTHER = "0xFFcf8FDEE72ac11b5c542428B35EEF5769C409f0"
REVIEWER = "0x22d491Bde2303f2f43325b2108D26f1eAbA1e32b"


def _imu(**changes: Any) -> dict[str, Any]:
    document: dict[str, Any] = {"name": "imu", "fields": {"ax": "float"}, "description": "x"}
    document.update(changes)
    return document


def test_lifecycle_to_approval_and_new_versions(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path)
    draft = catalog.create(_imu(), author=AUTHOR)
    assert (draft.id, draft.status, draft.author) == ("imu@1", "draft", AUTHOR)
    with pytest.raises(TemplateNotApproved):
        catalog.approved("imu@1")
    edited = catalog.edit("imu@1", {"fields": {"ax": "float", "ay": "float"}}, author=AUTHOR)
    assert list(edited.template.fields) == ["ax", "ay"]
    with pytest.raises(LifecycleConflict):
        catalog.review("imu@1", "approve", reviewer=REVIEWER)
    catalog.submit("imu@1", author=AUTHOR)
    with pytest.raises(TemplateImmutable) as under_review:
        catalog.edit("imu@1", _imu(), author=AUTHOR)
    assert under_review.value.status == "submitted"
    approved = catalog.review("imu@1", "approve", reviewer=REVIEWER, reason="fine")
    assert (approved.status, approved.reviewer, approved.reason) == ("approved", REVIEWER, "fine")
    assert catalog.approved("imu@1").fields.keys() == {"ax", "ay"}
    with pytest.raises(TemplateImmutable) as immutable:
        catalog.edit("imu@1", _imu(fields={"bx": "int"}), author=AUTHOR)
    assert immutable.value.status == "approved"
    assert catalog.approved("imu@1").fields.keys() == {"ax", "ay"}
    second = catalog.new_version("imu", {"fields": {"bx": "int"}}, author=OTHER)
    assert (second.id, second.status) == ("imu@2", "draft")
    with pytest.raises(TemplateExists):
        catalog.create(_imu(), author=AUTHOR)


def test_rejected_versions_may_be_edited_back_to_drafts(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path)
    catalog.create(_imu(), author=AUTHOR)
    catalog.submit("imu@1", author=AUTHOR)
    rejected = catalog.review("imu@1", "reject", reviewer=REVIEWER, reason="units?")
    assert (rejected.status, rejected.reason) == ("rejected", "units?")
    with pytest.raises(NotAuthor):
        catalog.edit("imu@1", _imu(), author=OTHER)
    again = catalog.edit("imu@1", _imu(description="m/s^2"), author=AUTHOR)
    assert (again.status, again.reviewer, again.reason) == ("draft", None, None)


def test_bad_documents_change_nothing(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path)
    with pytest.raises(TemplateInvalid) as invalid:
        catalog.create(_imu(fields={"Bad": "vector"}), author=AUTHOR)
    assert {p.path for p in invalid.value.problems} == {"fields.Bad"}
    with pytest.raises(TemplateInvalid):
        catalog.create([], author=AUTHOR)
    # true == 1 and 1.0 == 1 in Python: both were taken for version 1.
    for version in (2, True, 1.0, "1"):
        with pytest.raises(TemplateInvalid) as wrong_version:
            catalog.create(_imu(version=version), author=AUTHOR)
        assert [problem.to_json() for problem in wrong_version.value.problems] == [
            {"path": "version", "message": "must be the integer 1 (the next version)"}
        ]
    assert catalog.list() == []
    catalog.create(_imu(), author=AUTHOR)
    with pytest.raises(TemplateInvalid) as renamed:
        catalog.new_version("imu", _imu(name="gps"), author=AUTHOR)
    assert renamed.value.problems[0].path == "name"
    with pytest.raises(TemplateNotFound):
        catalog.new_version("gps", _imu(), author=AUTHOR)
    with pytest.raises(TemplateIdInvalid):
        catalog.get("imu")
    assert [v.id for v in catalog.list()] == ["imu@1"]


def test_submission_is_the_authors(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path)
    catalog.create(_imu(), author=AUTHOR)
    with pytest.raises(NotAuthor):
        catalog.submit("imu@1", author=OTHER)
    assert catalog.get("imu@1").status == "draft"


def test_the_catalog_survives_a_restart_and_is_bounded(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path, max_versions=2)
    catalog.create(_imu(), author=AUTHOR)
    catalog.submit("imu@1", author=AUTHOR)
    catalog.review("imu@1", "approve", reviewer=REVIEWER)
    catalog.create(_imu(name="gps"), author=AUTHOR)
    with pytest.raises(CatalogFull):
        catalog.new_version("imu", {"fields": {"x": "int"}}, author=AUTHOR)
    catalog.close()
    with (tmp_path / "catalog.log").open("ab") as journal:
        journal.write(b'{"id": "torn')
    reopened = Catalog(tmp_path)
    assert [(v.id, v.status) for v in reopened.list()] == [
        ("gps@1", "draft"),
        ("imu@1", "approved"),
    ]
    assert reopened.list(status="approved", limit=5)[0].reviewer == REVIEWER
    assert [v.id for v in reopened.list(after="gps@1")] == ["imu@1"]
    reopened.new_version("gps", {"fields": {"lat": "float"}}, author=AUTHOR)
    reopened.close()
    assert [v.id for v in Catalog(tmp_path).list(name="gps")] == ["gps@1", "gps@2"]


def test_the_catalog_opens_on_a_full_disk(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every open rewrote the journal, so a storage node whose disk had filled could not
    start again; an open now rewrites it only when enough of it is dead."""
    catalog = Catalog(tmp_path)
    catalog.create(_imu(), author=AUTHOR)
    catalog.submit("imu@1", author=AUTHOR)
    catalog.close()

    def no_space(path: Path, data: bytes, *, mode: int = 0o644) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(durable, "write_synced", no_space)
    reopened = Catalog(tmp_path)
    assert [(v.id, v.status) for v in reopened.list()] == [("imu@1", "submitted")]
    reopened.close()


def _big(name: str, fields: int = 200) -> dict[str, Any]:
    """A template of about ``fields`` * 20 bytes, as large as a stranger may make one."""
    return {"name": name, "fields": {f"field_{i:04d}": "float" for i in range(fields)}}


def test_the_catalog_is_bounded_in_bytes_and_an_edit_counts_its_growth(tmp_path: Path) -> None:
    """The count alone let 100,000 versions of 160 KB each take 79 GiB of memory."""
    measure = Catalog(tmp_path / "measure")
    measure.create(_big("a"), author=AUTHOR)
    measure.create(_big("b", 100), author=AUTHOR)
    sizes = [len(line) for line in (tmp_path / "measure" / "catalog.log").read_bytes().split()]
    limit = sum(sizes) + 1000
    catalog = Catalog(tmp_path / "c", max_bytes=limit)
    catalog.create(_big("a"), author=AUTHOR)
    catalog.create(_big("b", 100), author=AUTHOR)
    journal = (tmp_path / "c" / "catalog.log").read_bytes()
    with pytest.raises(CatalogFull, match=f"its limit of {limit} bytes of templates"):
        catalog.create(_big("c"), author=AUTHOR)
    with pytest.raises(CatalogFull, match="bytes of templates"):
        catalog.edit("b@1", {"fields": _big("b")["fields"]}, author=AUTHOR)
    assert (tmp_path / "c" / "catalog.log").read_bytes() == journal
    assert [v.id for v in catalog.list()] == ["a@1", "b@1"]
    assert len(catalog.get("b@1").template.fields) == 100
    catalog.edit("b@1", {"fields": {"x": "int"}}, author=AUTHOR)
    catalog.create(_big("c", 100), author=AUTHOR)
    catalog.close()
    reopened = Catalog(tmp_path / "c", max_bytes=limit)
    with pytest.raises(CatalogFull, match="bytes of templates"):
        reopened.create(_big("d"), author=AUTHOR)
    reopened.close()


def test_a_page_stops_at_its_byte_budget_but_holds_at_least_one_version(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path)
    for name in ("a", "b", "c"):
        catalog.create(_big(name), author=AUTHOR)
    size = len((tmp_path / "catalog.log").read_bytes()) // 3
    versions, more = catalog.page(limit=10, max_bytes=2 * size + 10)
    assert ([v.id for v in versions], more) == (["a@1", "b@1"], True)
    versions, more = catalog.page(after="b@1", limit=10, max_bytes=2 * size + 10)
    assert ([v.id for v in versions], more) == (["c@1"], False)
    versions, more = catalog.page(limit=10, max_bytes=1)
    assert ([v.id for v in versions], more) == (["a@1"], True)
    versions, more = catalog.page(limit=3, max_bytes=10 * size)
    assert ([v.id for v in versions], more) == (["a@1", "b@1", "c@1"], False)
    versions, more = catalog.page(limit=2, max_bytes=10 * size)
    assert ([v.id for v in versions], more) == (["a@1", "b@1"], True)


def test_approved_like_finds_the_approved_versions_of_the_same_fields(tmp_path: Path) -> None:
    """Those approved before its first search (the index is built then) and after it, in
    version order; never a draft, nor a template of other fields."""
    catalog = Catalog(tmp_path)
    fields = {"x": "float", "pose": {"container": {"y": "int"}}}

    def approved(version: int) -> None:
        if version == 1:
            catalog.create({"name": "b", "fields": fields}, author=AUTHOR)
        else:
            catalog.new_version("b", {"fields": fields}, author=AUTHOR)
        catalog.submit(f"b@{version}", author=AUTHOR)
        catalog.review(f"b@{version}", "approve", reviewer=REVIEWER)

    approved(1)
    catalog.create({"name": "a", "fields": {"x": "float"}}, author=AUTHOR)
    probe = parse_template({"name": "probe", "version": 1, "fields": fields})
    assert catalog.approved_like(probe) == ["b@1"]
    for version in range(2, 11):
        approved(version)
    catalog.new_version("b", {"fields": fields}, author=AUTHOR)
    assert catalog.approved_like(probe) == [f"b@{version}" for version in range(1, 11)]
    other = parse_template({"name": "probe", "version": 1, "fields": {"x": "int"}})
    assert catalog.approved_like(other) == []
    catalog.close()
