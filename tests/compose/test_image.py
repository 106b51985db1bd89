"""The image in Compose: the README's command builds it once and all five services run it.

With a `build` section on every service, Compose built the same image five times in parallel
and left four untagged 337 MB copies behind; a multi-stage Dockerfile under Docker's classic
builder leaves one more per build. ``scripts/test-compose.sh`` removes the test's image, lists
the images that exist, then runs ``make compose-up``: the only robocloud image that may have
appeared since is the tagged one, and no untagged image at all.
"""

from __future__ import annotations

import json

import pytest

from robocloud.config import SERVICES
from tests.compose.deployment import Deployment, docker, top_level_images

pytestmark = pytest.mark.compose


def image_id(reference: str) -> str:
    return docker("image", "inspect", "--format", "{{.Id}}", reference).strip()


def is_robocloud(image: dict[str, object]) -> bool:
    config = image["Config"]
    assert isinstance(config, dict)
    return (config.get("Labels") or {}).get("org.robocloud.image") == "robocloud"


def test_the_build_made_one_robocloud_image_and_nothing_untagged(
    deployment: Deployment,
) -> None:
    made = top_level_images() - deployment.images_before
    inspected = json.loads(docker("image", "inspect", *made)) if made else []
    robocloud_made = {image["Id"] for image in inspected if is_robocloud(image)}
    # The cache may hand back an image that existed under another tag: then nothing is new.
    extra = sorted(robocloud_made - {image_id(deployment.image)})
    assert extra == [], f"{len(extra)} robocloud images besides {deployment.image}"
    dangling = set(docker("images", "--quiet", "--no-trunc", "--filter", "dangling=true").split())
    untagged = sorted(dangling & made)
    assert untagged == [], f"the build left {len(untagged)} untagged images"


def test_every_service_runs_the_one_image(deployment: Deployment) -> None:
    built = image_id(deployment.image)
    assert {service: deployment.container(service)["Image"] for service in SERVICES} == {
        service: built for service in SERVICES
    }
