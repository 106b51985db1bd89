"""The Compose deployment under test, as ``scripts/test-compose.sh`` describes it.

The script deploys, then runs pytest with the deployment in the environment: the services'
published URLs in the SDK's own ``ROBOCLOUD_<SERVICE>_URL`` variables, the Compose project and
file (so tests can restart containers), the key of the identity the deployment lets write, and
the image tag it built with the images that existed before (so tests can count what it made).
"""

from __future__ import annotations

import json
import os
import subprocess
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import httpx

from robocloud.client import ServiceClient
from robocloud.config import SERVICES, service_url
from robocloud.identity import Identity

REQUIRED_ENV = (
    "ROBOCLOUD_COMPOSE_PROJECT",
    "ROBOCLOUD_COMPOSE_FILE",
    "ROBOCLOUD_COMPOSE_KEY",
    "ROBOCLOUD_IMAGE",
)
# Set even when empty: on a fresh machine no image exists before the build.
IMAGES_BEFORE_ENV = "ROBOCLOUD_COMPOSE_IMAGES_BEFORE"


class DeploymentMissingError(RuntimeError):
    """The tests were started without a deployment; they must fail, never skip."""


@dataclass(frozen=True)
class Deployment:
    """Published service URLs, the Compose project, the identity allowed to write, the image."""

    project: str
    compose_file: str
    urls: dict[str, str]
    identity: Identity
    image: str
    images_before: frozenset[str]

    @classmethod
    def from_env(cls) -> Deployment:
        missing = [name for name in REQUIRED_ENV if not os.environ.get(name)]
        if IMAGES_BEFORE_ENV not in os.environ:
            missing.append(IMAGES_BEFORE_ENV)
        if missing:
            raise DeploymentMissingError(
                f"{', '.join(missing)} not set: run these tests with `make test-compose`"
            )
        return cls(
            project=os.environ["ROBOCLOUD_COMPOSE_PROJECT"],
            compose_file=os.environ["ROBOCLOUD_COMPOSE_FILE"],
            urls={name: service_url(name) for name in SERVICES},
            identity=Identity.from_key(os.environ["ROBOCLOUD_COMPOSE_KEY"]),
            image=os.environ["ROBOCLOUD_IMAGE"],
            images_before=frozenset(os.environ[IMAGES_BEFORE_ENV].split()),
        )

    def client(self, service: str, identity: Identity | None = None) -> ServiceClient:
        """An SDK client for one service, signing as the deployment's identity by default."""
        return ServiceClient(self.urls[service], identity or self.identity, timeout=10)

    def compose(self, *args: str, timeout_s: float = 120) -> str:
        """Run ``docker compose`` on the deployment's project; fail with its output."""
        command = ["docker", "compose", "--project-name", self.project, "--file"]
        result = subprocess.run(
            [*command, self.compose_file, *args],
            capture_output=True,
            text=True,
            timeout=timeout_s,
            check=False,
        )
        if result.returncode != 0:
            raise RuntimeError(f"docker compose {' '.join(args)} failed:\n{result.stderr}")
        return result.stdout

    def restart(self, services: Sequence[str] = (), timeout_s: float = 60) -> None:
        """``docker compose restart`` (all services by default), then wait until ready."""
        self.compose("restart", *services)
        self.wait_ready(services or list(SERVICES), timeout_s)

    def recreate(self, timeout_s: float = 180) -> None:
        """New containers from the same image and volumes: only what is in a volume survives."""
        self.compose(
            "up", "--detach", "--wait", "--no-build", "--force-recreate", timeout_s=timeout_s
        )
        self.wait_ready(list(SERVICES))

    def container(self, service: str) -> dict[str, Any]:
        """``docker inspect`` of the service's container."""
        container_id = self.compose("ps", "--quiet", service).strip()
        if not container_id:
            raise RuntimeError(f"no container for {service} in project {self.project}")
        return dict(json.loads(docker("inspect", container_id))[0])

    def wait_ready(self, services: Sequence[str], timeout_s: float = 60) -> None:
        """Poll each service until it answers ``/readyz`` and Docker reports it healthy."""
        deadline = time.monotonic() + timeout_s
        for service in services:
            while not self._ready(service):
                if time.monotonic() > deadline:
                    logs = self.compose("logs", "--no-color", "--tail", "40", service)
                    raise TimeoutError(f"{service} not ready after {timeout_s} s:\n{logs}")
                time.sleep(0.2)

    def _ready(self, service: str) -> bool:
        """Ready through the published port, and healthy in Docker's eyes too."""
        try:
            if httpx.get(f"{self.urls[service]}/readyz", timeout=2).status_code != 200:
                return False
        except httpx.HTTPError:
            return False
        return bool(self.container(service)["State"]["Health"]["Status"] == "healthy")


def top_level_images() -> frozenset[str]:
    """Full IDs of the tagged and the untagged (dangling) images, no intermediate layers."""
    return frozenset(docker("images", "--quiet", "--no-trunc").split())


def docker(*args: str) -> str:
    """Run the ``docker`` CLI; fail with its output."""
    result = subprocess.run(
        ["docker", *args], capture_output=True, text=True, timeout=60, check=False
    )
    if result.returncode != 0:
        raise RuntimeError(f"docker {' '.join(args)} failed:\n{result.stderr}")
    return result.stdout
