#!/usr/bin/env bash
# Builds the wheelhouse the Dockerfile installs from, so the image builds with no registry:
# every pinned dependency of the `services` extra (constraints.txt) as a wheel, plus the build
# backend (setuptools, wheel) needed to install the project itself offline. It is rebuilt only
# when constraints.txt, pyproject.toml or this script change.
# Sourced by scripts/test-compose.sh; `bash scripts/docker/wheelhouse.sh` builds it alone.

# shellcheck source=scripts/docker/common.sh
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"

WHEELHOUSE="${BUILD_DIR}/wheels"

wheelhouse_key() {
    cat "${REPO_ROOT}/constraints.txt" "${REPO_ROOT}/pyproject.toml" \
        "${REPO_ROOT}/scripts/docker/wheelhouse.sh" | sha256sum | cut -d ' ' -f 1
}

build_wheelhouse() {
    local python key stamp="${BUILD_DIR}/wheels.key" staging="${BUILD_DIR}/wheels.partial"
    python="$(host_python)"
    key="$(wheelhouse_key)"
    if [[ -f "${stamp}" && "$(cat "${stamp}")" == "${key}" && -d "${WHEELHOUSE}" ]]; then
        log "wheelhouse up to date ($(find "${WHEELHOUSE}" -name '*.whl' | wc -l) wheels)"
        return 0
    fi
    log "building the wheelhouse in ${WHEELHOUSE}"
    rm -rf "${staging}" && mkdir -p "${staging}"
    "${python}" -m pip wheel --quiet --quiet --constraint "${REPO_ROOT}/constraints.txt" \
        --wheel-dir "${staging}" "${REPO_ROOT}[services]" || die "pip wheel failed"
    # The project is installed from the source copied into the image, not from this wheel.
    rm -f "${staging}"/robocloud-*.whl
    # Constrained too: wheel depends on packaging, whose newest release would otherwise sit
    # beside the pinned one and make the image's offline install unsolvable.
    "${python}" -m pip download --quiet --quiet --only-binary=:all: --dest "${staging}" \
        --constraint "${REPO_ROOT}/constraints.txt" "setuptools>=69" wheel \
        || die "pip download of the build backend failed"
    rm -rf "${WHEELHOUSE}" && mv "${staging}" "${WHEELHOUSE}"
    printf '%s\n' "${key}" >"${stamp}"
    log "wheelhouse ready ($(find "${WHEELHOUSE}" -name '*.whl' | wc -l) wheels)"
}

if [[ "${BASH_SOURCE[0]}" == "${0}" ]]; then
    set -euo pipefail
    build_wheelhouse
fi
