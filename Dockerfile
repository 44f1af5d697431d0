# The hypnerf service on CPU, serving the demo bundle (bundles/chair-demo).
#
#   docker build -t hypnerf .
#   docker run --rm -p 8000:8000 -e HYPNERF_API_KEYS=change-me -v hypnerf-state:/var/lib/hypnerf hypnerf
#   curl -H 'Authorization: Bearer change-me' localhost:8000/v1/model
#
# The container binds 0.0.0.0, so the server refuses to start without HYPNERF_API_KEYS (comma-separated
# bearer keys); /healthz and /readyz stay open for probes. Every HYPNERF_* setting (service/settings.py)
# can be passed with -e; the defaults are below.

ARG PYTHON_IMAGE=python:3.11-slim-bookworm

# -- builder: a venv with CPU torch, the project and the SDK; the hash-grid kernel compiled --------------
FROM ${PYTHON_IMAGE} AS builder

ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 HYPNERF_CACHE=/opt/hypnerf-ext
# g++ compiles the fused hash-grid kernel (torch C++ extension, built with ninja from the venv)
RUN apt-get update && apt-get install -y --no-install-recommends g++ && rm -rf /var/lib/apt/lists/*
RUN python -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH
# torch from PyTorch's CPU index, pinned as in pyproject.toml: the PyPI wheel bundles CUDA (gigabytes)
RUN pip install --upgrade pip setuptools wheel \
 && pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu

WORKDIR /src
COPY pyproject.toml README.md ./
COPY model model
COPY service service
COPY clients/python clients/python
# torch is already there (2.13.0+cpu satisfies the pin), so pip keeps it; the other dependencies come from PyPI
RUN pip install --no-build-isolation . \
 && pip install --no-build-isolation --no-deps ./clients/python
# build the kernel from the installed package (not /src) into HYPNERF_CACHE
RUN cd / && python -m model.nerf.encodings.kernels

# -- runtime ----------------------------------------------------------------------------------------------
FROM ${PYTHON_IMAGE} AS runtime

# The kernel is built with -march=native and its cache key names the compiler and the CPU: the same g++
# lets the container load the builder's binary, and rebuild it (once, into HYPNERF_CACHE) on another CPU.
RUN apt-get update && apt-get install -y --no-install-recommends g++ && rm -rf /var/lib/apt/lists/* \
 && groupadd --system --gid 10001 hypnerf \
 && useradd --system --uid 10001 --gid hypnerf --create-home --home-dir /home/hypnerf hypnerf \
 && mkdir -p /var/lib/hypnerf && chown hypnerf:hypnerf /var/lib/hypnerf

COPY --from=builder /opt/venv /opt/venv
COPY --from=builder --chown=hypnerf:hypnerf /opt/hypnerf-ext /opt/hypnerf-ext
WORKDIR /app
COPY bundles/chair-demo /app/bundles/chair-demo

ENV PATH=/opt/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    HYPNERF_CACHE=/opt/hypnerf-ext \
    MALLOC_MMAP_THRESHOLD_=34359738368 \
    MALLOC_TRIM_THRESHOLD_=34359738368 \
    THP_MEM_ALLOC_ENABLE=1 \
    HYPNERF_BUNDLE=/app/bundles/chair-demo \
    HYPNERF_HOST=0.0.0.0 \
    HYPNERF_PORT=8000 \
    HYPNERF_STATE_DIR=/var/lib/hypnerf \
    HYPNERF_WORKERS=1 \
    HYPNERF_RENDER_WORKERS=2 \
    HYPNERF_BROKER=sqlite

USER hypnerf
# the job database and the NeRF disk cache: keep them across container restarts
VOLUME ["/var/lib/hypnerf"]
EXPOSE 8000

HEALTHCHECK --interval=30s --timeout=5s --start-period=90s --retries=3 \
    CMD python -c "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:%s/readyz' % os.environ.get('HYPNERF_PORT', '8000'), timeout=4)"

CMD ["hypnerf", "serve", "--bundle", "/app/bundles/chair-demo"]
