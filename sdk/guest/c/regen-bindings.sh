#!/usr/bin/env bash
# Regenerates the committed C bindings in since_v0.1.0/ from wit/since_v0.1.0.
# Needs wit-bindgen-cli 0.60.0 (the release built on wasm-tools 0.254, like wasmtime 48):
#   cargo install wit-bindgen-cli@0.60.0 --locked        (about 5 minutes)
# CI never runs this: the generated files are committed, so building plugins needs no
# wit-bindgen. Only the WIT of an unreleased version may change; released ones are frozen.
set -euo pipefail
cd "$(dirname "$0")"
WIT=../../../wit/since_v0.1.0
version=$(wit-bindgen --version)
case "$version" in *" 0.60.0"*) ;; *) echo "need wit-bindgen 0.60.0, found: $version" >&2; exit 1 ;; esac
for world in horizon-policy priority-policy; do
    wit-bindgen c --no-object-file --world "$world" --out-dir since_v0.1.0 "$WIT"
done
