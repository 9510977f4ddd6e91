# CPU image of the ds3d service: python:3.11-slim, CPU torch pinned and installed first (so that
# no CUDA torch is pulled in), the locked dependencies (requirements/service.txt: the runtime and
# the [service] extra, each pinned and hash-checked), the project, the bundled models baked in,
# a non-root user, a health check on /readyz, uvicorn (through `ds3d-serve`, which runs itself
# under jemalloc: flat memory, ds3d_service/allocator.py). The container's CPU and memory limits
# size its worker processes and threads (DS3D_WORKERS, DS3D_TORCH_THREADS;
# ds3d_service/settings.py). Closed by default: it refuses to start without DS3D_API_KEYS (keys,
# or a file of keys mounted as a secret).
FROM python:3.11-slim

RUN apt-get update \
    && apt-get install -y --no-install-recommends libjemalloc2 \
    && rm -rf /var/lib/apt/lists/*

ARG TORCH_VERSION=2.13.0
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
# The lock to install, requirements/${LOCK}.txt: `--build-arg LOCK=ray` makes the image of the Ray
# Serve path (docker/k8s/rayservice.yaml).
ARG LOCK=service

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    DS3D_HOST=0.0.0.0 \
    DS3D_PORT=8000 \
    DS3D_MODEL_DIR=/app/models \
    DS3D_REQUIRE_API_KEYS=true

RUN pip install --no-cache-dir "torch==${TORCH_VERSION}" --index-url "${TORCH_INDEX_URL}"

WORKDIR /app
# Dependencies first, from the lock (a layer that survives code edits), then the models and the
# code. The project goes in with --no-deps: the lock is all it gets.
COPY requirements/${LOCK}.txt /tmp/requirements.txt
RUN pip install --no-cache-dir --require-hashes -r /tmp/requirements.txt \
    && useradd --create-home --uid 10001 --user-group ds3d
COPY pyproject.toml README.md ./
# The models before the code (they change less often); both before the install, which maps the
# package ds3d.models onto models/ (pyproject.toml). Editable, so that the image holds one copy.
COPY models models
COPY ds3d ds3d
COPY ds3d_service ds3d_service
RUN pip install --no-cache-dir --no-deps -e .

USER 10001:10001
# Build the retrieval indexes once, into the image (the user's cache), so replicas start fast.
RUN python -c "from ds3d.lifter import Lifter; Lifter.load()"
EXPOSE 8000
# Healthy = ready to take work (compose starts nginx once the replicas are healthy).
HEALTHCHECK --interval=15s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "-c", "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/readyz', timeout=4)"]
CMD ["ds3d-serve"]
