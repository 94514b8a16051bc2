# One dinerf robot (CPU). Used by the docker-compose.yml files of `dinerf-agent scenario compose`.
#   docker build -t dinerf-agent .
#   docker run --rm dinerf-agent --help
FROM python:3.11-slim

ENV PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1

# The CPU build of torch first (the default index would bring the CUDA build, gigabytes larger).
RUN pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu

WORKDIR /opt/dinerf
COPY pyproject.toml README.md* ./
COPY agent ./agent
COPY protocol ./protocol
COPY cli ./cli
RUN pip install .

# The run dir is a bind mount created by Docker (owned by root): the robot runs as root in its container.
WORKDIR /run/robot
ENTRYPOINT ["dinerf-agent"]
CMD ["--help"]
