"""The README's Python example, run as it is written against real services."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

from robocloud.identity import Identity
from robocloud.ingest import Ingest
from robocloud.storage import Storage
from services.storage.matcher import draft_template
from tests.bagfactory import typestore_for, write_bag
from tests.conftest import ServiceFactory
from tests.integration.services.storage.test_anchoring import Deployment
from tests.integration.services.storage.test_ingest_http import approved

README = Path(__file__).parents[3] / "README.md"


def python_example() -> str:
    """The README's one Python block, under "From Python"."""
    text = README.read_text()
    block = re.search(r"```python\n(.*?)```", text[text.index("### From Python") :], re.S)
    assert block is not None, "README.md has no Python block under From Python"
    return block.group(1)


def test_the_readme_s_python_example_runs(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    deployment = Deployment(service_factory, tmp_path)
    home = tmp_path / "home"
    identity.save(home / ".robocloud" / "keystore.json", "pw", scrypt_n=2**4)
    with Storage(deployment.storage.url, identity) as storage:
        imu = approved(storage, draft_template(typestore_for("ros1"), "sensor_msgs/msg/Imu"))
    assert imu == "imu@1"
    with Ingest(deployment.storage.url, identity) as ingest:
        ingest.bind(imu, topic="/imu")
    write_bag(tmp_path / "run.bag", "ros1", 60)
    example = tmp_path / "example.py"
    example.write_text(python_example())
    urls = {
        "ROBOCLOUD_CAS_URL": deployment.cas.url,
        "ROBOCLOUD_LEDGER_URL": deployment.ledger.url,
        "ROBOCLOUD_STORAGE_URL": deployment.storage.url,
    }
    done = subprocess.run(
        [sys.executable, str(example)],
        cwd=tmp_path,
        env={**os.environ, **urls, "HOME": str(home), "ROBOCLOUD_PASSPHRASE": "pw"},
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert done.returncode == 0, done.stderr
    status, anchored = done.stdout.splitlines()
    assert status == "succeeded {'imu@1': ['imu-1-0', 'imu-1-47']}"
    assert re.fullmatch(
        r"\{'x': 0\.1, 'y': 0\.2, 'z': 9\.81\} anchored in 0x[0-9a-f]{64}", anchored
    )
