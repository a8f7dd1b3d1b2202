# The Vox-E API: FastAPI under uvicorn, CPU-only torch (the API checks uploads with voxe_core.data; decoding them
# in full is the worker's ingest). It holds no worker code: it sends tasks by name (voxe_service.queue).
#   docker build -f docker/api.Dockerfile -t voxe-api .
FROM python:3.11-slim

ARG TORCH_SPEC="torch==2.13.0"
ARG TORCH_INDEX="https://download.pytorch.org/whl/cpu"

ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PYTHONPATH=/app

WORKDIR /app
# Dependencies first (cached layer): torch from the CPU index, then the project's own.
RUN pip install --index-url "$TORCH_INDEX" "$TORCH_SPEC"
COPY pyproject.toml README.md ./
COPY voxe_core ./voxe_core
COPY voxe_client ./voxe_client
COPY voxe_service ./voxe_service
COPY api ./api
COPY alembic.ini ./
RUN pip install ".[s3,postgres]" \
    && useradd --create-home --uid 10001 voxe \
    && mkdir -p /app/var && chown voxe /app/var
USER voxe

EXPOSE 8000
HEALTHCHECK --interval=15s --timeout=5s --start-period=30s --retries=5 \
    CMD python -c "import urllib.request,sys; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=4).status != 200)"
# The app runs `alembic upgrade head` (voxe_service/migrations) at startup. It listens on every interface, so authentication is on
# (VOXE_AUTH=auto): create keys with `docker compose exec api python -m api.admin create-key --name <who>`.
ENV VOXE_HOST=0.0.0.0
# On SIGTERM the API ends its event streams at once (clients resume with Last-Event-ID); any other response still
# open after 5 s is cut, so the shutdown (webhook sender, reaper) runs within docker stop's 10 s.
CMD ["uvicorn", "api.main:app", "--host", "0.0.0.0", "--port", "8000", "--proxy-headers", "--timeout-graceful-shutdown", "5"]
