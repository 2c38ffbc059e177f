# Tissue Twin workbench, CPU only: the dashboard and REST API on port 8000, the 3D viewer
# on 8001, with the demo session (generated and replayed at build time) and its replay job.
#
#   docker build -t tissuetwin:cpu .
#   docker run --rm -p 127.0.0.1:8000:8000 -p 127.0.0.1:8001:8001 tissuetwin:cpu
#
# then open http://127.0.0.1:8000. docker-compose.yml runs the same image as the workbench,
# a Dask scheduler and two workers, with PostgreSQL for the jobs.
ARG PYTHON_IMAGE=python:3.11-slim
FROM ${PYTHON_IMAGE}

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

# The system libraries open3d links against: libusb and OpenMP (what scripts/setup.sh
# installs), and EGL, GL and X11, which its module needs even headless (on a development
# machine they come with chromium; a slim image has none of them). Not version-pinned:
# Debian's archive drops superseded versions, and these get security updates.
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends libgomp1 libusb-1.0-0 libegl1 libgl1 libx11-6 \
    && rm -rf /var/lib/apt/lists/*

# torch first, pinned as in pyproject.toml, from PyTorch's CPU index: the image has no
# local wheel (scripts/setup.sh installs the machine's local CPU build), and PyPI's torch
# for Linux would pull gigabytes of CUDA libraries.
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
RUN pip install --index-url "${TORCH_INDEX_URL}" torch==2.13.0

RUN useradd --create-home --uid 1000 tissuetwin \
    && mkdir /data \
    && chown tissuetwin:tissuetwin /data
WORKDIR /opt/tissuetwin
COPY --chown=tissuetwin:tissuetwin pyproject.toml README.md ./
COPY --chown=tissuetwin:tissuetwin core ./core
COPY --chown=tissuetwin:tissuetwin app ./app
COPY --chown=tissuetwin:tissuetwin static ./static
# Editable: the dashboard's static/ is served from the source tree (app/server/main.py
# STATIC_DIR), which a plain `pip install .` leaves behind. torch==2.13.0+cpu satisfies
# the package's torch==2.13.0, so nothing is fetched twice.
RUN pip install -e . \
    && chown -R tissuetwin:tissuetwin /opt/tissuetwin

USER 1000:1000
# The demo session, generated and replayed once here (numba's compiled kernels are cached
# in the image too). /data is the volume docker-compose.yml shares with the Dask workers;
# Docker fills an empty named volume with this content the first time it is mounted.
ENV TISSUETWIN_DATA=/data
RUN tissuetwin demo --data /data --no-serve

EXPOSE 8000 8001
HEALTHCHECK --interval=10s --timeout=5s --start-period=300s --retries=3 \
    CMD ["python", "-c", "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/api/health', timeout=4)"]
# 0.0.0.0: the container's loopback is not reachable from outside it (the workbench
# warns that it has no authentication; publish the ports on the host's loopback).
CMD ["tissuetwin", "demo", "--data", "/data", "--host", "0.0.0.0", "--port", "8000"]
