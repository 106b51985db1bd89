#!/usr/bin/env bash
# Picks the base image for the Dockerfile's BASE_IMAGE: an explicit ROBOCLOUD_BASE_IMAGE, else
# python:3.11-slim when it is present or can be pulled, else an offline Debian bookworm image
# with Debian's python3.11 built by debootstrap from the apt mirror (ENVIRONMENT.md), because
# no container registry is reachable here.
# Sourced by scripts/test-compose.sh; `bash scripts/docker/base-image.sh` prints the choice.

# shellcheck source=scripts/docker/common.sh
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"

DEBIAN_SUITE="bookworm"
# Packages on top of minbase: the interpreter and venv (ensurepip) the Dockerfile relies on.
BASE_PACKAGES="python3,python3-venv"

# The first Debian mirror apt on this host uses, so debootstrap goes where apt goes.
debian_mirror() {
    local uri
    uri="$(grep -hoE '^URIs:[[:space:]]*\S+' /etc/apt/sources.list.d/*.sources 2>/dev/null |
        awk '{print $2}' | grep -v security | head -n 1 || true)"
    if [[ -z "${uri}" && -f /etc/apt/sources.list ]]; then
        uri="$(awk '$1 == "deb" && $3 !~ /security/ {print $2; exit}' /etc/apt/sources.list)"
    fi
    printf '%s\n' "${uri:-http://deb.debian.org/debian}"
}

can_use_default_base() {
    docker image inspect "${DEFAULT_BASE_IMAGE}" >/dev/null 2>&1 && return 0
    log "trying to pull ${DEFAULT_BASE_IMAGE}"
    timeout 60 docker pull --quiet "${DEFAULT_BASE_IMAGE}" >/dev/null 2>&1
}

build_offline_base() {
    command -v debootstrap >/dev/null 2>&1 || apt_install debootstrap
    local rootfs mirror
    rootfs="$(mktemp -d /var/tmp/robocloud-rootfs.XXXXXX)"
    mirror="$(debian_mirror)"
    log "debootstrap ${DEBIAN_SUITE} (minbase + ${BASE_PACKAGES}) from ${mirror}"
    if ! debootstrap --variant=minbase --include="${BASE_PACKAGES}" \
        "${DEBIAN_SUITE}" "${rootfs}" "${mirror}" >"${BUILD_DIR}/debootstrap.log" 2>&1; then
        tail -n 30 "${BUILD_DIR}/debootstrap.log" >&2
        rm -rf "${rootfs}"
        die "debootstrap failed (log: ${BUILD_DIR}/debootstrap.log)"
    fi
    rm -rf "${rootfs}"/var/cache/apt/archives/*.deb "${rootfs}"/var/lib/apt/lists/*
    log "importing ${OFFLINE_BASE_IMAGE}"
    tar -C "${rootfs}" -c . | docker import \
        --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
        --change 'ENV LANG=C.UTF-8' \
        --change 'CMD ["python3"]' \
        - "${OFFLINE_BASE_IMAGE}" >/dev/null || die "docker import of the base image failed"
    rm -rf "${rootfs}"
}

# Prints the image to pass as BASE_IMAGE, building the offline one when needed.
ensure_base_image() {
    mkdir -p "${BUILD_DIR}"
    if [[ -n "${ROBOCLOUD_BASE_IMAGE:-}" ]]; then
        printf '%s\n' "${ROBOCLOUD_BASE_IMAGE}"
    elif can_use_default_base; then
        printf '%s\n' "${DEFAULT_BASE_IMAGE}"
    elif docker image inspect "${OFFLINE_BASE_IMAGE}" >/dev/null 2>&1; then
        log "no registry: reusing the offline base image ${OFFLINE_BASE_IMAGE}"
        printf '%s\n' "${OFFLINE_BASE_IMAGE}"
    else
        log "no registry: building the offline base image ${OFFLINE_BASE_IMAGE}"
        build_offline_base
        printf '%s\n' "${OFFLINE_BASE_IMAGE}"
    fi
}

if [[ "${BASH_SOURCE[0]}" == "${0}" ]]; then
    set -euo pipefail
    ensure_base_image
fi
