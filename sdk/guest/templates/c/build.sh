#!/usr/bin/env bash
# Builds and checks the C template: bound.c -> bound.wasm (in OUT, default the current dir).
# Usage: build.sh [OUT]   (needs clang/wasi-libc and a `kairos` binary on PATH or in $KAIROS)
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
SDK="$HERE/../../c"
OUT="${1:-.}"
KAIROS="${KAIROS:-kairos}"
mkdir -p "$OUT"
clang --target=wasm32-wasi -O2 -ffp-contract=off -mexec-model=reactor -Wall -Wextra -Werror \
    -Wl,--strip-all -I "$SDK/since_v0.3.0" -I "$SDK" -o "$OUT/bound.core.wasm" "$HERE/bound.c" \
    "$SDK/since_v0.3.0/horizon_policy.c" "$SDK/kairos_world_stub.c"
"$KAIROS" plugin componentize "$OUT/bound.core.wasm" --world horizon -o "$OUT/bound.wasm"
"$KAIROS" plugin check "$OUT/bound.wasm" --param bound=0.05 --no-cache --cases 50
