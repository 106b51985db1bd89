#!/usr/bin/env bash
# `make compose-down`: stops the Compose deployment (`docker compose down`, arguments passed
# on: `--volumes` deletes the data too), then the Docker engine if `make compose-up` started it
# and no container is left on it, so that a machine goes back to the state it was in.
set -euo pipefail

SCRIPTS="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
# shellcheck source=scripts/docker/engine.sh
source "${SCRIPTS}/engine.sh"

main() {
    cd "${REPO_ROOT}"
    if ! docker info >/dev/null 2>&1; then
        log "no Docker engine is running: nothing to stop"
        return 0
    fi
    log "docker compose down $*"
    docker compose down "$@" || die "docker compose down failed"
    local pid
    pid="$(dockerd_left_running)" || return 0
    if [[ -n "$(docker ps --quiet)" ]]; then
        log "leaving dockerd (pid ${pid}) running: other containers run on it"
        return 0
    fi
    stop_dockerd "${pid}"
}

main "$@"
