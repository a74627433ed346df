# DanceGraph: one image for api, worker and graphstore; the `fbx` target adds Blender (bpy) for
# the FBX worker. Build: docker build -t dancegraph .   (or: docker compose build)
FROM node:20-bookworm-slim AS frontend
# the preview page: three.js bundled by esbuild from the pinned lock file (see frontend/)
WORKDIR /src/frontend
COPY frontend/package.json frontend/package-lock.json ./
RUN npm ci --no-audit --no-fund
COPY frontend/build.mjs ./
COPY frontend/src ./src
RUN DANCEGRAPH_PREVIEW_OUT=/preview npm run build

FROM python:3.11-slim-bookworm AS base
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 \
    DANCEGRAPH_HOME=/data DANCEGRAPH_STORE=/data/store
RUN apt-get update \
 && apt-get install -y --no-install-recommends libsndfile1 ffmpeg curl \
 && rm -rf /var/lib/apt/lists/*
WORKDIR /app
COPY pyproject.toml README.md ./
COPY dancegraph ./dancegraph
COPY services ./services
COPY --from=frontend /preview ./services/preview_static
COPY migrations ./migrations
COPY alembic.ini openapi.yaml ./
COPY scripts ./scripts
RUN pip install --extra-index-url https://download.pytorch.org/whl/cpu -e . \
 && python -m dancegraph.music.weights fetch
RUN useradd --create-home --uid 1000 dancegraph && mkdir -p /data && chown dancegraph /data
USER dancegraph
# compile the numba kernels into the user's cache once, at build time (dancegraph.jit)
RUN python -m dancegraph.jit
VOLUME ["/data"]
EXPOSE 8000
CMD ["uvicorn", "services.api.app:app", "--host", "0.0.0.0", "--port", "8000"]

FROM base AS fbx
USER root
RUN apt-get update \
 && apt-get install -y --no-install-recommends libx11-6 libxrender1 libxfixes3 libxi6 libxkbcommon0 \
      libxext6 libxt6 libsm6 libice6 libgl1 libopengl0 \
 && rm -rf /var/lib/apt/lists/* \
 && python -m venv /opt/blender && /opt/blender/bin/pip install "numpy<2" bpy==5.0.1
ENV DANCEGRAPH_BLENDER_PYTHON=/opt/blender/bin/python
USER dancegraph
