# One dinerf robot (CPU). Used by the docker-compose.yml files of `dinerf-agent scenario compose`.
#   docker build -t dinerf-agent .
#   docker run --rm dinerf-agent --help
#   docker run --rm dinerf-agent scenario list      (the scenarios ship inside the package)
# Without a registry (podman, a Debian base made by debootstrap, torch from pip's configured
# index or find-links): `dinerf-agent scenario image`, which passes the build args below.
ARG BASE_IMAGE=python:3.11-slim
FROM ${BASE_IMAGE}

# torch: what to install and from which index. The CPU index by default (the default index would
# bring the CUDA build, gigabytes larger); an empty TORCH_INDEX uses pip's own configuration.
ARG TORCH_SPEC=torch==2.13.0
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu

ENV PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 \
    VIRTUAL_ENV=/opt/venv PATH=/opt/venv/bin:$PATH

# iproute2: `tc` for the link-emulation services of the compose files (they run as root with
# NET_ADMIN in a robot's network namespace; the robot itself never does).
RUN apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends iproute2 \
    && rm -rf /var/lib/apt/lists/*

# A venv, so that the same steps work on python:3.11-slim and on a Debian base (whose system
# Python refuses pip installs, PEP 668).
RUN python3 -m venv /opt/venv && pip install "${TORCH_SPEC}" ${TORCH_INDEX:+--index-url "$TORCH_INDEX"}

WORKDIR /opt/dinerf
# The dependencies first, in their own layer (from pyproject.toml only, on empty packages), so
# a code change rebuilds only the last, quick layer.
COPY pyproject.toml ./
RUN mkdir -p agent protocol cli scenarios && touch README.md agent/__init__.py protocol/__init__.py cli/__init__.py \
        scenarios/__init__.py \
    && pip install . && pip uninstall -y -q dinerf && rm -rf agent protocol cli scenarios build ./*.egg-info README.md
COPY README.md* ./
COPY agent ./agent
COPY protocol ./protocol
COPY cli ./cli
COPY scenarios ./scenarios
RUN pip install --no-deps . && rm -rf build ./*.egg-info

# A robot never needs root. Compose runs it as the host user (DINERF_UID/DINERF_GID) so that the
# run dirs it writes through the bind mount belong to whoever started the swarm.
RUN useradd --create-home --uid 1000 dinerf && mkdir -p /run/robot && chown dinerf:dinerf /run/robot
USER dinerf
WORKDIR /run/robot
# Healthy while the robot finishes rounds (or has finished); SfM on a big folder may take a while.
HEALTHCHECK --interval=60s --timeout=20s --start-period=30m --retries=10 CMD ["dinerf-agent", "-q", "health", "/run/robot"]
ENTRYPOINT ["dinerf-agent"]
CMD ["--help"]
