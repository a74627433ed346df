#!/usr/bin/env bash
# Install Blender as a Python module (bpy 5.0.1) for FBX export, in its own virtual environment.
#
# Idempotent: re-running changes nothing once everything is in place. bpy is GPL and pins numpy<2,
# so it lives in <repo>/.venv-blender (or $BLENDER_VENV), never in the service's venv; DanceGraph
# talks to it through a child process (dancegraph/motion/fbx.py). bpy 5.0.1 is the newest release
# with a CPython 3.11 wheel, so the venv needs Python 3.11 ($PYTHON, default python3.11).
#
# System libraries: bpy links libX11, libXrender, libXfixes, libXi, libxkbcommon, libXext, libXt,
# libSM, libICE and libGL/libOpenGL (found with `ldd` on every .so in the wheel). On a bare
# Debian/Ubuntu they are apt-get installed, and only the packages that are missing.
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${BLENDER_VENV:-$REPO/.venv-blender}"
PYTHON="${PYTHON:-python3.11}"
BPY_VERSION="5.0.1"
DEB_PACKAGES=(libx11-6 libxrender1 libxfixes3 libxi6 libxkbcommon0 libxext6 libxt6 libsm6 libice6 libgl1 libopengl0)

if command -v dpkg-query >/dev/null 2>&1; then
  missing=()
  for pkg in "${DEB_PACKAGES[@]}"; do
    if ! dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed"; then
      missing+=("$pkg")
    fi
  done
  if ((${#missing[@]})); then
    echo "installing system libraries: ${missing[*]}"
    SUDO=""
    if [[ $(id -u) -ne 0 ]]; then SUDO="sudo"; fi
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y --no-install-recommends "${missing[@]}"
  fi
else
  echo "not a Debian-like system: make sure these libraries are installed: ${DEB_PACKAGES[*]}" >&2
fi

if [[ ! -x "$VENV/bin/python" ]]; then
  command -v "$PYTHON" >/dev/null 2>&1 || PYTHON=python3
  if ! "$PYTHON" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
    echo "bpy $BPY_VERSION needs CPython 3.11; set PYTHON to a python3.11 interpreter" >&2
    exit 1
  fi
  echo "creating $VENV"
  "$PYTHON" -m venv "$VENV"
fi

if ! "$VENV/bin/python" -c "import importlib.metadata as m, sys; sys.exit(m.version('bpy') != '$BPY_VERSION')" 2>/dev/null; then
  "$VENV/bin/python" -m pip install --quiet --upgrade pip
  "$VENV/bin/python" -m pip install --quiet "bpy==$BPY_VERSION"
fi

# Smoke test: Blender loads and has the BVH importer and the FBX exporter.
"$VENV/bin/python" - <<'PY'
import bpy
assert hasattr(bpy.ops.import_anim, "bvh") and hasattr(bpy.ops.export_scene, "fbx")
print(f"bpy {bpy.app.version_string} ready")
PY
echo "FBX export ready: DANCEGRAPH_BLENDER_PYTHON=$VENV/bin/python (the default location)"
