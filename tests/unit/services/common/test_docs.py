"""``/docs`` and ``/redoc`` work offline: every asset they reference is served by the service."""

from __future__ import annotations

import asyncio
import re
from pathlib import Path

import httpx
import pytest

from services.common.app import create_app
from services.common.settings import ServiceSettings

REFERENCE = re.compile(r"""(?:src|href|spec-url)="([^"]*)"|url: '([^']*)'""")
EXPECTED_TYPES = {".js": "text/javascript", ".css": "text/css", ".png": "image/png"}


def fetch_all(tmp_path: Path, page: str) -> tuple[str, dict[str, httpx.Response]]:
    """The page's HTML and the answer to every URL it references."""
    settings = ServiceSettings(service="test", data_dir=tmp_path, auth="signed")
    app = create_app("test", settings)

    async def go() -> tuple[str, dict[str, httpx.Response]]:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            html = (await client.get(page)).text
            references = {a or b for a, b in REFERENCE.findall(html)}
            return html, {url: await client.get(url) for url in references}

    return asyncio.run(go())


@pytest.mark.parametrize(
    ("page", "assets"),
    [
        ("/docs", {"swagger-ui-bundle.js", "swagger-ui.css", "favicon.png"}),
        ("/redoc", {"redoc.standalone.js", "favicon.png"}),
    ],
)
def test_docs_pages_reference_only_assets_the_service_serves(
    tmp_path: Path, page: str, assets: set[str]
) -> None:
    html, answers = fetch_all(tmp_path, page)
    assert "http://" not in html
    assert "https://" not in html
    assert set(answers) == {"/openapi.json"} | {f"/docs/assets/{name}" for name in assets}
    for url, answer in answers.items():
        assert answer.status_code == 200, url
        suffix = Path(url).suffix
        if suffix in EXPECTED_TYPES:
            assert answer.headers["content-type"].startswith(EXPECTED_TYPES[suffix]), url
            assert len(answer.content) > 4000, f"{url} is the real asset, not a stub"
    assert answers["/openapi.json"].json()["info"]["title"] == "robocloud test"


def test_swagger_ui_bundle_is_the_real_library(tmp_path: Path) -> None:
    """The bundle defines what the page calls, in a version that renders OpenAPI 3.1."""
    html, answers = fetch_all(tmp_path, "/docs")
    bundle = answers["/docs/assets/swagger-ui-bundle.js"].text
    assert "SwaggerUIBundle(" in html
    assert "SwaggerUIBundle" in bundle
    assert answers["/openapi.json"].json()["openapi"].startswith("3.1.")
    assert "isOAS31" in bundle, "Swagger UI renders OpenAPI 3.1 only from version 5 on"


def test_unknown_asset_is_404(tmp_path: Path) -> None:
    settings = ServiceSettings(service="test", data_dir=tmp_path, auth="signed")
    app = create_app("test", settings)

    async def go() -> httpx.Response:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            return await client.get("/docs/assets/../../etc/passwd")

    assert asyncio.run(go()).status_code == 404
