# One dinerf robot (CPU). Used by the docker-compose.yml files of `dinerf-agent scenario compose`.
#   docker build -t dinerf-agent .
#   docker run --rm dinerf-agent --help
#   docker run --rm dinerf-agent scenario list      (the scenarios ship inside the package)
FROM python:3.11-slim

ENV PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1

# The CPU build of torch first (the default index would bring the CUDA build, gigabytes larger).
RUN pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu

WORKDIR /opt/dinerf
COPY pyproject.toml README.md* ./
COPY agent ./agent
COPY protocol ./protocol
COPY cli ./cli
COPY scenarios ./scenarios
RUN pip install .

# A robot never needs root. Compose runs it as the host user (DINERF_UID/DINERF_GID) so that the
# run dirs it writes through the bind mount belong to whoever started the swarm.
RUN useradd --create-home --uid 1000 dinerf && mkdir -p /run/robot && chown dinerf:dinerf /run/robot
USER dinerf
WORKDIR /run/robot
# Healthy while the robot finishes rounds (or has finished); SfM on a big folder may take a while.
HEALTHCHECK --interval=60s --timeout=20s --start-period=30m --retries=10 CMD ["dinerf-agent", "-q", "health", "/run/robot"]
ENTRYPOINT ["dinerf-agent"]
CMD ["--help"]
