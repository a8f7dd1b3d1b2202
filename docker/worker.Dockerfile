# A Vox-E GPU worker: Celery consuming the `gpu` queue (job stages and upload ingests), one task at a time per GPU,
# CUDA torch. It holds no API code (the service core and voxe_core only).
#   docker build -f docker/worker.Dockerfile -t voxe-worker .
# Run one container per GPU (concurrency 1); models come from the Hugging Face cache in HF_HOME.
FROM nvidia/cuda:12.6.3-cudnn-runtime-ubuntu24.04

# The torch the tests run (.ci/setup, the API image), in its CUDA 12.6 build (2.13 is built for CUDA 12.6 and 13.0).
ARG TORCH_SPEC="torch==2.13.0"
ARG TORCH_INDEX="https://download.pytorch.org/whl/cu126"

ENV DEBIAN_FRONTEND=noninteractive PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 PYTHONPATH=/app PATH=/opt/venv/bin:$PATH \
    HF_HOME=/models/hf VOXE_MODEL_DIR=/models/voxe VOXE_DEVICE=cuda \
    PYTORCH_NVML_BASED_CUDA_CHECK=1 \
    REMAP_SIGTERM=SIGQUIT
# REMAP_SIGTERM: `docker stop` and Kubernetes send SIGTERM, whose warm shutdown waits for the running stage
# (hours) and is then killed with its message unacknowledged; Celery's cold shutdown hands the message
# back to the broker at once and the next worker resumes the stage from its last checkpoint.

# A C compiler and Python's headers: torch.compile (the SDS step's VAE encoder) builds Triton's helpers at run time.
RUN apt-get update \
    && apt-get install -y --no-install-recommends python3 python3-venv python3-dev build-essential ca-certificates \
    && rm -rf /var/lib/apt/lists/* \
    && python3 -m venv /opt/venv

WORKDIR /app
RUN pip install --index-url "$TORCH_INDEX" "$TORCH_SPEC"
COPY pyproject.toml README.md ./
COPY voxe_core ./voxe_core
COPY voxe_client ./voxe_client
COPY voxe_service ./voxe_service
COPY worker ./worker
RUN pip install ".[s3,postgres]" \
    && useradd --create-home --uid 10001 voxe \
    && mkdir -p /models /app/var && chown voxe /models /app/var
USER voxe

# prefork with one process: soft / hard time limits work and the process is recycled every
# VOXE_WORKER_MAX_TASKS_PER_CHILD tasks (models stay loaded in between).
CMD ["celery", "-A", "worker.celery_app", "worker", "-Q", "gpu", "--concurrency", "1", "--pool", "prefork", \
     "-n", "gpu@%h", "-l", "info"]
