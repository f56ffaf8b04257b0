# lightfield: API and workers. Two runtime targets:
#   docker build --target cpu  -t lightfield:cpu  .   # API, CPU workers, embedded mode
#   docker build --target cuda -t lightfield:cuda .   # GPU workers (one job per GPU)
# Base images are pinned by tag; pin by digest in your registry mirror for reproducible builds.
# Every pip install goes through constraints.txt, so no dependency can swap the torch build.

ARG PYTHON_IMAGE=python:3.11.11-slim-bookworm
ARG CUDA_IMAGE=nvidia/cuda:12.8.1-cudnn-runtime-ubuntu24.04

# ---------------------------------------------------------------- the package sources (listed once)
FROM scratch AS sources
WORKDIR /src
COPY pyproject.toml README.md ./
COPY core ./core
COPY jobs ./jobs
COPY service ./service
COPY worker ./worker
COPY cli ./cli
COPY assets ./assets
COPY bench ./bench

# ---------------------------------------------------------------- CPU: build the venv
FROM ${PYTHON_IMAGE} AS build-cpu
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
RUN python -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH
WORKDIR /src
COPY constraints.txt ./
RUN pip install -c constraints.txt --extra-index-url "${TORCH_INDEX}" torch==2.13.0
COPY --from=sources /src ./
# the API serves /usdz, which needs the `usd` extra (usd-core)
RUN pip install -c constraints.txt --extra-index-url "${TORCH_INDEX}" ".[usd]"

# ---------------------------------------------------------------- CPU runtime
FROM ${PYTHON_IMAGE} AS cpu
RUN groupadd --system --gid 10001 lightfield \
    && useradd --system --uid 10001 --gid lightfield --create-home --home-dir /home/lightfield lightfield \
    && mkdir -p /data && chown lightfield:lightfield /data
COPY --from=build-cpu /opt/venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    LIGHTFIELD_DATA_DIR=/data
WORKDIR /home/lightfield
USER 10001:10001
VOLUME ["/data"]
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s \
    CMD ["python", "-c", "import urllib.request,sys; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/healthz').status != 200)"]
# Binding beyond loopback requires LIGHTFIELD_API_KEYS (the server refuses otherwise).
CMD ["lightfield", "serve", "--host", "0.0.0.0", "--port", "8000"]

# ---------------------------------------------------------------- CUDA: build the venv
FROM ${CUDA_IMAGE} AS build-cuda
ARG TORCH_INDEX=https://download.pytorch.org/whl/cu128
ENV DEBIAN_FRONTEND=noninteractive PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends software-properties-common gpg-agent \
    && add-apt-repository -y ppa:deadsnakes/ppa \
    && apt-get update \
    && apt-get install -y --no-install-recommends python3.11 python3.11-venv \
    && rm -rf /var/lib/apt/lists/*
RUN python3.11 -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH
WORKDIR /src
COPY constraints.txt ./
RUN grep -v '^torch==' constraints.txt > constraints-cuda.txt \
    && pip install -c constraints-cuda.txt --index-url "${TORCH_INDEX}" torch==2.13.0
COPY --from=sources /src ./
RUN pip install -c constraints-cuda.txt --extra-index-url "${TORCH_INDEX}" .

# ---------------------------------------------------------------- CUDA runtime (GPU worker)
FROM ${CUDA_IMAGE} AS cuda
ENV DEBIAN_FRONTEND=noninteractive
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends software-properties-common gpg-agent \
    && add-apt-repository -y ppa:deadsnakes/ppa \
    && apt-get update \
    && apt-get install -y --no-install-recommends python3.11 \
    && apt-get purge -y software-properties-common gpg-agent && apt-get autoremove -y \
    && rm -rf /var/lib/apt/lists/* \
    && groupadd --system --gid 10001 lightfield \
    && useradd --system --uid 10001 --gid lightfield --create-home --home-dir /home/lightfield lightfield \
    && mkdir -p /data /models && chown lightfield:lightfield /data
COPY --from=build-cuda /opt/venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    LIGHTFIELD_DATA_DIR=/data \
    LIGHTFIELD_MODEL_DIRS=/models
WORKDIR /home/lightfield
USER 10001:10001
VOLUME ["/data"]
CMD ["lightfield", "worker", "--name", "gpu"]
