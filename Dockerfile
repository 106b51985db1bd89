# One image for every robocloud service; compose.yaml picks the service with its command.
#
# BASE_IMAGE is python:3.11-slim where a registry is reachable; without one,
# scripts/docker/base-image.sh builds an offline Debian bookworm base with python3.11.
# When .docker-build/wheels/ exists (scripts/docker/wheelhouse.sh) everything installs from it
# with no network at all; without it, pip installs the pinned versions from the index.
ARG BASE_IMAGE=python:3.11-slim

FROM ${BASE_IMAGE} AS build
LABEL org.robocloud.image=robocloud
ENV PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_NO_CACHE_DIR=1 \
    PATH=/opt/robocloud/bin:$PATH
# Dependencies first, so that a code change does not reinstall them. `.docker-buil[d]` is an
# optional source: it matches nothing when no wheelhouse was built.
COPY constraints.txt .docker-buil[d] /build/
RUN python3 -m venv /opt/robocloud \
    && if ls /build/wheels/*.whl >/dev/null 2>&1; then \
        pip install --no-index --find-links /build/wheels /build/wheels/*.whl; \
    fi
COPY . /app
RUN if ls /build/wheels/*.whl >/dev/null 2>&1; then \
        pip install --no-index --find-links /build/wheels --no-deps /app; \
    else \
        pip install --constraint /build/constraints.txt "/app[services]"; \
    fi \
    && rm -rf /app/build /app/*.egg-info /app/clients/*.egg-info

# The runtime stage carries the venv and the source tree (for data files that services find
# beside their code, such as contracts/build), never the wheelhouse.
FROM ${BASE_IMAGE} AS runtime
LABEL org.robocloud.image=robocloud
ENV PATH=/opt/robocloud/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    ROBOCLOUD_HOST=0.0.0.0 \
    ROBOCLOUD_DATA_DIR=/data
# A fixed unprivileged user that owns /data, so a fresh named volume mounted there inherits
# that ownership.
RUN useradd --system --uid 10001 --user-group --home-dir /data --no-create-home robocloud \
    && mkdir /data && chown robocloud:robocloud /data
COPY --from=build /opt/robocloud /opt/robocloud
COPY --from=build /app /app
WORKDIR /app
USER robocloud
EXPOSE 8080 8545 8082 8083 8084
CMD ["robocloud", "--help"]
