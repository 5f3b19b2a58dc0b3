#!/usr/bin/env bash
# Builds and checks the Python template: app.py -> bound_py.wasm (in OUT, default the current dir).
# Usage: build.sh [OUT]   (needs componentize-py on PATH or in $COMPONENTIZE_PY, and `kairos`)
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
OUT="${1:-.}"
KAIROS="${KAIROS:-kairos}"
COMPONENTIZE_PY="${COMPONENTIZE_PY:-componentize-py}"
mkdir -p "$OUT/wit"
"$KAIROS" plugin wit --out "$OUT/wit" >/dev/null
"$COMPONENTIZE_PY" -d "$OUT/wit" -w horizon-policy componentize app -p "$HERE" -o "$OUT/bound_py.wasm" >/dev/null
# Default settings: what a user who starts from the template runs.
"$KAIROS" plugin check "$OUT/bound_py.wasm" --cache-dir "$OUT/cache"
