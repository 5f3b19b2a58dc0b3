#!/usr/bin/env bash
# Builds every shipped policy plugin from source into plugins/build/ (gitignored), then runs
# `kairos plugin check` on each (which also fills plugins/build/cache with their compiled
# code, so the tests load them in milliseconds).
#
#   C plugins:      clang --target=wasm32-wasi -> core module -> `kairos plugin componentize`
#   Python plugins: componentize-py (from .venv, see scripts/install-plugin-toolchains.sh)
#
# Needs: scripts/install-plugin-toolchains.sh (once). The server's own build needs none of it.
set -euo pipefail
cd "$(dirname "$0")/.."

OUT=plugins/build
# The WIT version the shipped plugins target; plugins/c/compat/ keeps older ones built.
VERSION=since_v0.2.0
WIT=wit/$VERSION
SDK=sdk/guest/c
CACHE="$OUT/cache"
mkdir -p "$OUT"

for tool in clang wasm-ld; do
    command -v "$tool" >/dev/null || { echo "plugins/build.sh: $tool not found; run scripts/install-plugin-toolchains.sh" >&2; exit 1; }
done
COMPONENTIZE_PY=$PWD/.venv/bin/componentize-py
[ -x "$COMPONENTIZE_PY" ] || COMPONENTIZE_PY=$(command -v componentize-py || true)
[ -n "$COMPONENTIZE_PY" ] || { echo "plugins/build.sh: componentize-py not found; run scripts/install-plugin-toolchains.sh" >&2; exit 1; }

# KAIROS_BIN: a kairos binary built already (scripts/test.sh passes the one its test build made,
# so that CI compiles the workspace once, with one feature set).
if [ -n "${KAIROS_BIN:-}" ]; then
    [ -x "$KAIROS_BIN" ] || { echo "plugins/build.sh: KAIROS_BIN=$KAIROS_BIN is not an executable" >&2; exit 1; }
    KAIROS=$KAIROS_BIN
else
    echo "building the kairos binary (for componentize and check)"
    cargo build --quiet --locked -p kairos-cli --bin kairos
    KAIROS=target/debug/kairos
fi

# -ffp-contract=off: the native twins never fuse multiply-adds, so neither may the plugins.
CFLAGS=(--target=wasm32-wasi -O2 -ffp-contract=off -mexec-model=reactor -Wall -Wextra -Werror
    -Wl,--strip-all)

build_c() { # source world [version]: plugins/c/<source>.c -> $OUT/<basename of source>.wasm
    local src=$1 world=$2 version=${3:-$VERSION}
    local name
    name=$(basename "$src")
    clang "${CFLAGS[@]}" -I "$SDK/$version" -I "$SDK" -o "$OUT/$name.core.wasm" "plugins/c/$src.c" \
        "$SDK/$version/${world}_policy.c" "$SDK/kairos_world_stub.c"
    "$KAIROS" plugin componentize "$OUT/$name.core.wasm" --world "$world" -o "$OUT/$name.wasm"
}

build_py() { # name world
    local name=$1 world=$2
    "$COMPONENTIZE_PY" -d "$WIT" -w "$world-policy" componentize app \
        -p "plugins/python/$name" -o "$OUT/${name}_py.wasm" >/dev/null
    echo "$OUT/${name}_py.wasm: $(stat -c %s "$OUT/${name}_py.wasm") bytes, world $world-policy"
}

build_c threshold horizon
build_c static horizon
build_c steady horizon
build_c contact horizon
# The load-aware horizon reads the server's load: kairos:policy@0.3.0.
build_c load_aware horizon since_v0.3.0
build_c fifo priority
build_c plas priority
build_c kairos priority
build_c srw priority
# A 0.1.0 plugin, kept to prove the server still loads plugins built for the older version.
build_c compat/fifo_v0_1 priority since_v0.1.0
build_py kairos priority

# Conformance gate; parameters where a policy requires them.
check() { "$KAIROS" plugin check --cache-dir "$CACHE" --cases 100 "$@" >/dev/null || {
    "$KAIROS" plugin check --cache-dir "$CACHE" --cases 100 "$@"; exit 1; }; }
check "$OUT/threshold.wasm"
check "$OUT/static.wasm" --param h=8
check "$OUT/steady.wasm"
check "$OUT/contact.wasm"
check "$OUT/load_aware.wasm"
check "$OUT/fifo.wasm"
check "$OUT/plas.wasm"
check "$OUT/kairos.wasm"
check "$OUT/srw.wasm"
check "$OUT/fifo_v0_1.wasm"
check "$OUT/kairos_py.wasm" --memory-mib 256
# The author templates (sdk/guest/templates), so they never rot.
KAIROS="$PWD/$KAIROS" bash sdk/guest/templates/c/build.sh "$OUT/templates" >/dev/null
KAIROS="$PWD/$KAIROS" COMPONENTIZE_PY="$COMPONENTIZE_PY" \
    bash sdk/guest/templates/python/build.sh "$OUT/templates" >/dev/null
echo "templates built and checked: $OUT/templates/bound.wasm $OUT/templates/bound_py.wasm"
echo "plugins built and checked: $(cd "$OUT" && ls ./*.wasm | grep -v core | tr '\n' ' ')"
