#!/usr/bin/env bash
# Regenerates the committed C bindings: for every wit/since_vX.Y.Z/, the directory
# since_vX.Y.Z/ here (one .c/.h pair per world).
# Needs wit-bindgen-cli 0.60.0 (the release built on wasm-tools 0.254, like wasmtime 48):
#   cargo install wit-bindgen-cli@0.60.0 --locked        (about 5 minutes)
# CI never runs this: the generated files are committed, so building plugins needs no
# wit-bindgen. Only the WIT of an unreleased version may change; released ones are frozen, so
# regenerating them must leave their bindings byte-identical (check with git diff).
set -euo pipefail
cd "$(dirname "$0")"
version=$(wit-bindgen --version)
case "$version" in *" 0.60.0"*) ;; *) echo "need wit-bindgen 0.60.0, found: $version" >&2; exit 1 ;; esac
for wit in ../../../wit/since_v*/; do
    dir=$(basename "$wit")
    for world in horizon-policy priority-policy; do
        wit-bindgen c --no-object-file --world "$world" --out-dir "$dir" "$wit"
    done
done
