# One image for every process of docker-compose.yml: the API (uvicorn), the Celery workers and the MLflow
# server. Build: docker build -t denoiser-service .   GPU build: add --build-arg TORCH_INDEX_URL= (see below).
#
# Debian 12 (bookworm) is pinned rather than the floating python:3.11-slim tag: it is the system the project is
# developed and tested on, and it ships the libllvm19 package installed below.
FROM python:3.11-slim-bookworm

# libllvm19: Mitsuba's vectorized CPU backend (llvm_ad_rgb) needs LLVM 19; Dr.Jit would otherwise pick the
# system's default LLVM, and Debian's LLVM 15 crashes it. model/data/mitsuba_backend.py finds this library.
# gcc, libc6-dev: the fused models' native CPU kernels are compiled on the machine that runs them, on first use
# (-march=native; model/ops/native); without a compiler the steps run torch's ops instead.
RUN apt-get update \
 && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends libllvm19 gcc libc6-dev \
 && rm -rf /var/lib/apt/lists/*

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    DENOISER_DATA_DIR=/data

WORKDIR /app

# torch==2.13.0 is pinned exactly in pyproject.toml. On Linux the default package index serves that version as
# a CUDA build (several GB, needed by the GPU worker only), so by default torch is installed first from PyTorch's
# CPU wheel index; the later install sees 2.13.0+cpu satisfy the pin (a local "+cpu" label matches ==2.13.0).
# The GPU worker's image is built with TORCH_INDEX_URL empty, which takes the default CUDA build instead.
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu

# Dependencies first, read from pyproject.toml, so editing the code does not reinstall them. psycopg2: the MLflow
# server of docker-compose.yml keeps runs and the model registry in PostgreSQL; it is installed here rather than
# in pyproject.toml because only that deployment needs it.
COPY pyproject.toml README.md ./
RUN python -c "import tomllib; print('\n'.join(tomllib.load(open('pyproject.toml','rb'))['project']['dependencies']))" \
        > /tmp/requirements.txt \
 && if [ -n "$TORCH_INDEX_URL" ]; then \
        pip install --index-url "$TORCH_INDEX_URL" "$(grep '^torch==' /tmp/requirements.txt)"; \
    fi \
 && pip install -r /tmp/requirements.txt "psycopg2-binary>=2.9" \
 && rm /tmp/requirements.txt

COPY model ./model
COPY core ./core
COPY service ./service
COPY workers ./workers
COPY cli ./cli
COPY client ./client
# The pretrained models (weights + manifests); the installed package finds them through its settings
# (DENOISER_PRETRAINED_DIR, core/settings.py).
COPY pretrained ./pretrained
ENV DENOISER_PRETRAINED_DIR=/app/pretrained
# --no-deps: everything is installed above; this adds the packages and the `denoiser` console script.
RUN pip install --no-deps .

# An unprivileged user owns the data folders; a new named volume mounted on them takes this ownership.
RUN useradd --create-home --uid 10001 denoiser \
 && mkdir -p /data /mlflow \
 && chown denoiser:denoiser /data /mlflow
USER denoiser

EXPOSE 8000
# The API listens on every interface here: it refuses to start without a real DENOISER_API_KEY.
ENV DENOISER_REQUIRE_API_KEY=true
# One uvicorn process: inference sessions keep their models and history in its memory (mirrored to Redis).
# --ws-max-size: a session stream's frame (one WebSocket message) may be as large as DENOISER_MAX_FRAME_BYTES.
CMD ["uvicorn", "service.http.app:app", "--host", "0.0.0.0", "--port", "8000", "--ws-max-size", "268435456"]
