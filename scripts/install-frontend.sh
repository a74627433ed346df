#!/usr/bin/env bash
# Build the preview page (frontend/ → services/preview_static/, which the API and
# `dancegraph preview` serve): `npm ci` of the pinned lock file (three.js, esbuild, and
# playwright-core for the browser test; nothing is fetched at run time), then the esbuild bundle.
# With DANCEGRAPH_INSTALL_CHROMIUM=1 (set by .ci/run) it also installs Debian's chromium, which
# tests/services/test_preview_browser.py drives. Idempotent: npm ci is skipped while the lock
# file is unchanged.
set -euo pipefail
cd "$(dirname "$0")/.."

if ! command -v npm >/dev/null 2>&1; then
  echo "install-frontend: npm not found (Node.js 20+ needed); the preview page is not built" >&2
  exit 1
fi
stamp=frontend/node_modules/.installed-$(sha256sum frontend/package-lock.json | cut -c1-16)
if [ ! -f "$stamp" ]; then
  (cd frontend && npm ci --no-audit --no-fund --loglevel=error)
  touch "$stamp"
fi
(cd frontend && npm run --silent build)

if [ "${DANCEGRAPH_INSTALL_CHROMIUM:-0}" = "1" ] && [ ! -x /usr/bin/chromium ]; then
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
fi
