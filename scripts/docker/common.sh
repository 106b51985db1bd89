# shellcheck shell=bash disable=SC2034
# Shared by the scripts in scripts/docker/: paths, logging and failing loudly.
# Sourced, never run: it only defines variables (used by the sourcing scripts, hence SC2034)
# and functions.

REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
# Everything generated for a build lives here; it is git-ignored and sent in the build context
# (wheels only; see .dockerignore).
BUILD_DIR="${REPO_ROOT}/.docker-build"
# The offline base image built when python:3.11-slim cannot be pulled.
OFFLINE_BASE_IMAGE="${ROBOCLOUD_OFFLINE_BASE_IMAGE:-robocloud-base:bookworm}"
DEFAULT_BASE_IMAGE="python:3.11-slim"

log() {
    printf '[%s] %s\n' "$(date +%H:%M:%S)" "$*" >&2
}

die() {
    printf '[%s] ERROR: %s\n' "$(date +%H:%M:%S)" "$*" >&2
    exit 1
}

apt_install() {
    log "installing with apt: $*"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq || die "apt-get update failed"
    apt-get install -y -qq --no-install-recommends "$@" >/dev/null || die "apt-get install $* failed"
}

# The Python that builds the wheelhouse and runs the host-side tests: the project's venv.
host_python() {
    local python="${REPO_ROOT}/.venv/bin/python"
    [[ -x "${python}" ]] || die "${python} is missing: run 'make test-compose' (it creates the venv)"
    printf '%s\n' "${python}"
}
