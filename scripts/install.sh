#!/usr/bin/env bash
# One install step for a fresh machine: the project venv (.venv), BeatNet's weights taken from its
# pinned wheel, the compiled kernels, and Blender's own venv (.venv-blender) for FBX export.
# Idempotent: a second run only checks. Set DANCEGRAPH_SKIP_BLENDER=1 to skip FBX support.
set -euo pipefail
cd "$(dirname "$0")/.."

PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null 2>&1 || PY=python3

if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
stamp=.venv/.installed-$(sha256sum pyproject.toml | cut -c1-16)
if [ ! -f "$stamp" ]; then
  .venv/bin/pip install -q --upgrade pip
  # torch is pinned to the CPU build that this machine kind keeps on disk (see pyproject.toml).
  .venv/bin/pip install -q -e '.[dev]'
  rm -f .venv/.installed-*
  touch "$stamp"
fi

.venv/bin/python -m dancegraph.music.weights fetch

# compile the numba kernels once into the per-user cache (a later run only loads them)
.venv/bin/python -m dancegraph.jit

if [ "${DANCEGRAPH_SKIP_BLENDER:-0}" != "1" ]; then
  bash scripts/install-blender.sh
fi

# the browser preview page (Node.js + npm); DANCEGRAPH_SKIP_FRONTEND=1 skips it
if [ "${DANCEGRAPH_SKIP_FRONTEND:-0}" != "1" ]; then
  bash scripts/install-frontend.sh
fi
