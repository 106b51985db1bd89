"""The bounded h11 server protocol against uvicorn's httptools, on the same cas app, same run.

Every service runs uvicorn's h11 protocol behind a request-head meter (services/common/
server.py) instead of httptools, which has no bound on a header. This measures what that
costs, on one cas process of each kind started side by side:

1. small requests: sequential ``GET /healthz`` over one kept-alive connection;
2. uploads: a signed ``POST /api/v0/add`` of one file (hashing, chunking and storing
   included, as a robot sees it).

It prints each figure and the ratio bounded/httptools (above 1: the bounded server is faster).

    python bench/http_server.py [--requests 2000] [--upload-mib 128]
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "clients")]

from robocloud.identity import Identity  # noqa: E402
from robocloud.signing import sign_request  # noqa: E402
from tests.procs import ServiceProcess, audience_of, free_port  # noqa: E402

HTTPTOOLS_CAS = """
import uvicorn
from services.cas.app import CasSettings, build_app
from services.common.settings import load_settings
settings = load_settings("cas", CasSettings)
uvicorn.run(build_app(settings), host="127.0.0.1", port=settings.port, http="httptools",
            log_config=None, access_log=False)
"""


def start_httptools_cas(data_dir: Path) -> subprocess.Popen[bytes]:
    port = free_port()
    env = {
        **os.environ,
        "ROBOCLOUD_PORT": str(port),
        "ROBOCLOUD_DATA_DIR": str(data_dir),
        "ROBOCLOUD_AUTH": "signed",
        "ROBOCLOUD_CAS_GC_INTERVAL_S": "0",
        "ROBOCLOUD_LOG_LEVEL": "WARNING",
    }
    process = subprocess.Popen(
        [sys.executable, "-c", HTTPTOOLS_CAS], env=env, cwd=REPO, stderr=subprocess.DEVNULL
    )
    process.url = f"http://127.0.0.1:{port}"  # type: ignore[attr-defined]
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"{process.url}/readyz", timeout=1).status_code == 200:  # type: ignore[attr-defined]
                return process
        except httpx.HTTPError:
            time.sleep(0.1)
    raise RuntimeError("the httptools cas did not start")


def requests_per_second(url: str, count: int) -> float:
    with httpx.Client(base_url=url) as client:
        client.get("/healthz")
        started = time.perf_counter()
        for _ in range(count):
            client.get("/healthz").raise_for_status()
        return count / (time.perf_counter() - started)


def upload_mib_per_second(url: str, data: bytes, robot: Identity) -> float:
    boundary = "benchboundary"
    body = (
        f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="f"\r\n'
        "Content-Type: application/octet-stream\r\n\r\n"
    ).encode()
    body += data + f"\r\n--{boundary}--\r\n".encode()
    digest = hashlib.sha256(body).hexdigest()
    headers = sign_request(robot.account, audience_of(url), "POST", "/api/v0/add", "", digest)
    headers["Content-Type"] = f"multipart/form-data; boundary={boundary}"
    started = time.perf_counter()
    response = httpx.post(f"{url}/api/v0/add", content=body, headers=headers, timeout=600)
    response.raise_for_status()
    return len(data) / (1 << 20) / (time.perf_counter() - started)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--requests", type=int, default=2000)
    parser.add_argument("--upload-mib", type=int, default=128)
    args = parser.parse_args()
    robot = Identity.generate()
    data = os.urandom(args.upload_mib << 20)
    with tempfile.TemporaryDirectory() as tmp:
        bounded = ServiceProcess(
            "cas", Path(tmp) / "bounded", {"ROBOCLOUD_CAS_GC_INTERVAL_S": "0"}
        ).start()
        baseline = start_httptools_cas(Path(tmp) / "httptools")
        try:
            urls = {"bounded h11": bounded.url, "httptools": baseline.url}  # type: ignore[attr-defined]
            small = {name: requests_per_second(url, args.requests) for name, url in urls.items()}
            upload = {name: upload_mib_per_second(url, data, robot) for name, url in urls.items()}
        finally:
            bounded.stop()
            baseline.terminate()
            baseline.wait()
    for name in urls:
        print(f"{name:12} GET /healthz {small[name]:8.0f} req/s   add {upload[name]:7.1f} MiB/s")
    print(
        f"ratio bounded/httptools: requests {small['bounded h11'] / small['httptools']:.2f}, "
        f"upload {upload['bounded h11'] / upload['httptools']:.2f}"
    )


if __name__ == "__main__":
    main()
