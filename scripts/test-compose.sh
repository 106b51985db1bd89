#!/usr/bin/env bash
# `make test-compose`: deploy robocloud with Docker Compose and test it from the host.
#
# Installs and starts the Docker engine and Compose v2 when missing, builds the wheelhouse and
# (without a registry) an offline base image, builds the image, runs `docker compose up -d
# --wait` under its own project name on free loopback ports, runs pytest tests/compose, and
# always finishes with `docker compose down -v` (and stops dockerd if it started it). Runs are
# serialised by a lock, since several people share one engine and one working tree.
# It never skips: anything that cannot be set up fails the run.
#
# Environment: ROBOCLOUD_COMPOSE_PROJECT (default robocloud-compose-test),
# ROBOCLOUD_COMPOSE_AUTH (default registered, with the test identity allowlisted),
# ROBOCLOUD_BASE_IMAGE (skip the base image choice), PYTEST_ARGS (extra pytest arguments).
set -euo pipefail

SCRIPTS="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
# shellcheck source=scripts/docker/engine.sh
source "${SCRIPTS}/docker/engine.sh"
# shellcheck source=scripts/docker/base-image.sh
source "${SCRIPTS}/docker/base-image.sh"
# shellcheck source=scripts/docker/wheelhouse.sh
source "${SCRIPTS}/docker/wheelhouse.sh"

PROJECT="${ROBOCLOUD_COMPOSE_PROJECT:-robocloud-compose-test}"
export ROBOCLOUD_IMAGE="robocloud:${PROJECT}"
COMPOSE_FILE_PATH="${REPO_ROOT}/compose.yaml"
SERVICES=(cas ledger storage broker fl)
DEPLOYED=0

compose() {
    docker compose --project-name "${PROJECT}" --file "${COMPOSE_FILE_PATH}" "$@"
}

# On failure the containers' last log lines are the first thing anyone needs.
finish() {
    local status=$?
    trap - EXIT INT TERM
    if ((DEPLOYED)); then
        if ((status != 0)); then
            log "failed (exit ${status}); last container logs:"
            compose logs --no-color --tail 40 >&2 || true
        fi
        log "docker compose down -v"
        compose down --volumes --remove-orphans --timeout 10 >&2 || status=1
    fi
    stop_engine_if_started || status=1
    exit "${status}"
}

free_ports() {
    "$(host_python)" - "$1" <<'PY'
import socket, sys
sockets = [socket.socket() for _ in range(int(sys.argv[1]))]
for sock in sockets:
    sock.bind(("127.0.0.1", 0))
print(" ".join(str(sock.getsockname()[1]) for sock in sockets))
PY
}

# A throwaway key for this run: its address is the one the deployment allows to write.
new_test_key() {
    "$(host_python)" -c 'from eth_account import Account; print(Account.create().key.hex())'
}

key_address() {
    "$(host_python)" -c 'import sys; from eth_account import Account
print(Account.from_key(sys.argv[1]).address)' "$1"
}

timed() {
    local started=${SECONDS}
    "$@"
    log "$1 took $((SECONDS - started)) s"
}

# The build stage is tagged too, so that pruning the images a rebuild left untagged never
# removes the cached dependency layer it sits on.
build_image() {
    local base stage
    base="$(ensure_base_image)"
    log "building ${ROBOCLOUD_IMAGE} on ${base}"
    for stage in build runtime; do
        local tag="${ROBOCLOUD_IMAGE}"
        [[ "${stage}" == build ]] && tag="${ROBOCLOUD_IMAGE}-build"
        docker build --quiet --target "${stage}" --tag "${tag}" \
            --build-arg "BASE_IMAGE=${base}" "${REPO_ROOT}" >/dev/null || die "docker build failed"
    done
    docker image prune --force --filter "label=org.robocloud.image=robocloud" >/dev/null
}

deploy() {
    local ports key service index=0
    read -r -a ports <<<"$(free_ports "${#SERVICES[@]}")"
    key="$(new_test_key)"
    export ROBOCLOUD_AUTH="${ROBOCLOUD_COMPOSE_AUTH:-registered}"
    ROBOCLOUD_ALLOWED_ADDRESSES="$(key_address "${key}")"
    export ROBOCLOUD_ALLOWED_ADDRESSES ROBOCLOUD_COMPOSE_KEY="${key}"
    export ROBOCLOUD_COMPOSE_PROJECT="${PROJECT}" ROBOCLOUD_COMPOSE_FILE="${COMPOSE_FILE_PATH}"
    for service in "${SERVICES[@]}"; do
        export "ROBOCLOUD_${service^^}_PUBLISH_PORT=${ports[index]}"
        export "ROBOCLOUD_${service^^}_URL=http://127.0.0.1:${ports[index]}"
        index=$((index + 1))
    done
    DEPLOYED=1
    log "docker compose up -d --wait (project ${PROJECT}, auth ${ROBOCLOUD_AUTH})"
    compose up --detach --wait --wait-timeout 120 --no-build >&2 || die "compose up failed"
}

run_tests() {
    log "pytest tests/compose"
    # shellcheck disable=SC2086
    "${REPO_ROOT}/.venv/bin/pytest" "${REPO_ROOT}/tests/compose" -p no:cacheprovider ${PYTEST_ARGS:-}
}

main() {
    cd "${REPO_ROOT}"
    mkdir -p "${BUILD_DIR}"
    # Machine-wide: every clone shares the one engine and the project name.
    exec 9>"${TMPDIR:-/tmp}/robocloud-test-compose.lock"
    log "waiting for the test-compose lock"
    flock --timeout 1800 9 || die "another test-compose run held the lock for 30 minutes"
    trap finish EXIT
    trap 'exit 130' INT
    trap 'exit 143' TERM
    timed ensure_docker
    # A run killed before its trap ran leaves its project behind; start clean.
    compose down --volumes --remove-orphans --timeout 5 >/dev/null 2>&1 || true
    timed build_wheelhouse
    timed build_image
    timed deploy
    timed run_tests
}

main "$@"
