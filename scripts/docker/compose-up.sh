#!/usr/bin/env bash
# `make compose-up`: the Compose deployment on any machine, a fresh offline one included.
#
# Installs and starts the Docker engine and Compose v2 when missing (the engine is left
# running; `make compose-down` stops it), builds the wheelhouse and, without a registry, the
# offline base image when they are missing or stale, then runs
# `docker compose up -d --wait --build` with that base image. Arguments go to `up`.
# The image that a rebuild replaced is removed once no container uses it, so that repeated
# runs leave one robocloud image behind, not a trail of untagged ones.
#
# Environment: everything compose.yaml reads (ROBOCLOUD_IMAGE, ROBOCLOUD_BASE_IMAGE,
# ROBOCLOUD_AUTH, ROBOCLOUD_<SERVICE>_PUBLISH_PORT, ...), COMPOSE_PROJECT_NAME (default
# robocloud), ROBOCLOUD_COMPOSE_WAIT_TIMEOUT_S (default 300: how long `--wait` waits for
# every service to be healthy).
set -euo pipefail

SCRIPTS="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
# shellcheck source=scripts/docker/engine.sh
source "${SCRIPTS}/engine.sh"
# shellcheck source=scripts/docker/base-image.sh
source "${SCRIPTS}/base-image.sh"
# shellcheck source=scripts/docker/wheelhouse.sh
source "${SCRIPTS}/wheelhouse.sh"

IMAGE="${ROBOCLOUD_IMAGE:-robocloud:latest}"

image_id() {
    docker image inspect --format '{{.Id}}' "$1" 2>/dev/null || true
}

# The replaced image is untagged now; `docker image rm` refuses it while any container, even a
# stopped one, still uses it, and that refusal is the check.
remove_replaced_image() {
    local replaced=$1 current
    current="$(image_id "${IMAGE}")"
    [[ -n "${replaced}" && "${replaced}" != "${current}" ]] || return 0
    if docker image rm "${replaced}" >/dev/null 2>&1; then
        log "removed the image this build replaced (${replaced:7:12})"
    else
        log "kept the replaced image ${replaced:7:12}: a container still uses it"
    fi
}

# The ports inside the containers (ARCHITECTURE.md); the host side is whatever was published.
declare -A CONTAINER_PORTS=([cas]=8080 [ledger]=8545 [storage]=8082 [broker]=8083 [fl]=8084)

print_urls() {
    local service published
    for service in cas ledger storage broker fl; do
        published="$(docker compose port "${service}" "${CONTAINER_PORTS[${service}]}")" ||
            die "no published port for ${service}"
        printf '  %-8s http://%s/docs\n' "${service}" "${published}"
    done
}

main() {
    cd "${REPO_ROOT}"
    mkdir -p "${BUILD_DIR}"
    ensure_docker
    build_wheelhouse
    ROBOCLOUD_BASE_IMAGE="$(ensure_base_image)"
    export ROBOCLOUD_BASE_IMAGE ROBOCLOUD_IMAGE="${IMAGE}"
    local replaced
    replaced="$(image_id "${IMAGE}")"
    log "docker compose up -d --wait --build (image ${IMAGE} on ${ROBOCLOUD_BASE_IMAGE})"
    docker compose up --detach --wait --build \
        --wait-timeout "${ROBOCLOUD_COMPOSE_WAIT_TIMEOUT_S:-300}" "$@" ||
        die "docker compose up failed; see 'docker compose logs'"
    remove_replaced_image "${replaced}"
    log "robocloud is up:"
    print_urls >&2
}

main "$@"
