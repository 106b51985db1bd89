#!/usr/bin/env bash
# `make test-compose`: deploy robocloud with the README's own command and test it from the host.
#
# Installs and starts the Docker engine and Compose v2 when missing, removes this test's image
# and volumes so that it starts from a clean state, runs `make compose-up` (the README's
# command: wheelhouse, base image, `docker compose up -d --wait --build`) under its own
# project name and image tag on free loopback ports, runs pytest tests/compose, and always
# finishes with `docker compose down -v`, removes the image, and stops dockerd if it started it.
# Runs are serialised by a lock, since several people share one engine.
# It never skips: anything that cannot be set up fails the run.
#
# Environment: ROBOCLOUD_COMPOSE_PROJECT (default robocloud-compose-test),
# ROBOCLOUD_COMPOSE_AUTH (default registered, with the test identity allowlisted),
# ROBOCLOUD_BASE_IMAGE (skip the base image choice), PYTEST_ARGS (extra pytest arguments).
set -euo pipefail

SCRIPTS="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
# shellcheck source=scripts/docker/engine.sh
source "${SCRIPTS}/docker/engine.sh"

PROJECT="${ROBOCLOUD_COMPOSE_PROJECT:-robocloud-compose-test}"
# Its own tag, so that the test never replaces or removes the image of a local deployment.
export ROBOCLOUD_IMAGE="robocloud:${PROJECT}"
# `make compose-up` runs `docker compose` in the checkout: this makes it the test's project.
export COMPOSE_PROJECT_NAME="${PROJECT}"
COMPOSE_FILE_PATH="${REPO_ROOT}/compose.yaml"
COMPOSE_UP_LOG="${BUILD_DIR}/compose-up.log"
SERVICES=(cas ledger storage broker fl)
DEPLOYED=0

compose() {
    docker compose --project-name "${PROJECT}" --file "${COMPOSE_FILE_PATH}" "$@"
}

# The project's containers, network and volumes, and the image the test builds.
remove_deployment() {
    compose down --volumes --remove-orphans --timeout 10 >&2 || return 1
    if docker image inspect "${ROBOCLOUD_IMAGE}" >/dev/null 2>&1; then
        docker image rm "${ROBOCLOUD_IMAGE}" >/dev/null || return 1
    fi
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
        log "docker compose down -v, and removing ${ROBOCLOUD_IMAGE}"
        remove_deployment || status=1
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

# What the README's newcomer has: no image of this deployment, no volume. A run killed before
# its trap ran leaves its project behind; this removes it too.
clean_state() {
    remove_deployment || die "cannot remove the previous test deployment"
    if docker image inspect "${ROBOCLOUD_IMAGE}" >/dev/null 2>&1; then
        die "${ROBOCLOUD_IMAGE} still exists"
    fi
    local volumes
    volumes="$(docker volume ls --quiet --filter "label=com.docker.compose.project=${PROJECT}")"
    [[ -z "${volumes}" ]] || die "volumes of ${PROJECT} still exist: ${volumes}"
    log "clean state: no ${ROBOCLOUD_IMAGE}, no volume of ${PROJECT}"
}

configure() {
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
}

# The README's command, as a newcomer types it; its full output (the image build included)
# goes to a log whose tail is shown on failure.
compose_up() {
    # tests/compose/test_image.py checks what appeared besides these.
    ROBOCLOUD_COMPOSE_IMAGES_BEFORE="$(docker images --quiet --no-trunc | sort -u | tr '\n' ' ')"
    export ROBOCLOUD_COMPOSE_IMAGES_BEFORE
    DEPLOYED=1
    log "make compose-up (project ${PROJECT}, image ${ROBOCLOUD_IMAGE}, auth ${ROBOCLOUD_AUTH})"
    if ! make --no-print-directory -C "${REPO_ROOT}" compose-up >"${COMPOSE_UP_LOG}" 2>&1; then
        tail -n 60 "${COMPOSE_UP_LOG}" >&2
        die "make compose-up failed (log: ${COMPOSE_UP_LOG})"
    fi
    grep -E '^\[[0-9:]{8}\]|^  [a-z]+ +http' "${COMPOSE_UP_LOG}" >&2 || true
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
    timed clean_state
    configure
    timed compose_up
    timed run_tests
}

main "$@"
