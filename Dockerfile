# One image for every robocloud service; compose.yaml builds it once and runs each service
# from it with its own command.
#
# BASE_IMAGE is python:3.11-slim where a registry is reachable; without one,
# scripts/docker/base-image.sh builds an offline Debian bookworm base with python3.11.
# When .docker-build/wheels/ exists (scripts/docker/wheelhouse.sh) everything installs from it
# with no network at all; without it, pip installs the pinned versions from the index.
#
# One stage on purpose: the only builder here is Docker's classic one (no buildx), which leaves
# every stage but the last behind as an untagged image on each build. The price is the
# wheelhouse's layer (about 26 MB) in images built offline.
ARG BASE_IMAGE=python:3.11-slim

FROM ${BASE_IMAGE}
LABEL org.robocloud.image=robocloud
ENV PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_NO_CACHE_DIR=1 \
    PATH=/opt/robocloud/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    ROBOCLOUD_HOST=0.0.0.0 \
    ROBOCLOUD_DATA_DIR=/data
# A fixed unprivileged user that owns /data, so a fresh named volume mounted there inherits
# that ownership.
RUN useradd --system --uid 10001 --user-group --home-dir /data --no-create-home robocloud \
    && mkdir /data && chown robocloud:robocloud /data
# Dependencies first, so that a code change does not reinstall them. `.docker-buil[d]` is an
# optional source: it matches nothing when no wheelhouse was built.
COPY constraints.txt .docker-buil[d] /build/
RUN python3 -m venv /opt/robocloud \
    && if ls /build/wheels/*.whl >/dev/null 2>&1; then \
        pip install --no-index --find-links /build/wheels /build/wheels/*.whl; \
    fi
# The source tree stays at /app: services find data files beside their code (contracts/build).
COPY . /app
RUN if ls /build/wheels/*.whl >/dev/null 2>&1; then \
        pip install --no-index --find-links /build/wheels --no-deps /app; \
    else \
        pip install --constraint /build/constraints.txt "/app[services]"; \
    fi \
    && rm -rf /app/build /app/*.egg-info /app/clients/*.egg-info
WORKDIR /app
USER robocloud
EXPOSE 8080 8545 8082 8083 8084
CMD ["robocloud", "--help"]
