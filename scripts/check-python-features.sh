#!/usr/bin/env bash
# Checks that the Python extension (sdk/python, which maturin builds on its own) resolves the same
# crate features as the workspace build, so that `pip install ./sdk/python` after `cargo test
# --workspace` reuses the workspace's compiled crates instead of compiling them again with other
# features (see the feature-unification note in sdk/python/Cargo.toml and docs/BENCHMARKS.md,
# "CI time"). Compares the target-side crates only (`no-proc-macro`, no build dependencies):
# cargo tree prints a crate built for the host and for the target alike, so mixing them would let
# a host variant hide a target mismatch.
set -euo pipefail
cd "$(dirname "$0")/.."

tree() { cargo tree --locked --prefix none -f '{p} [{f}]' "$@" | sed 's/ (\*)$//' | sort -u; }
workspace=$(tree --workspace -e normal,dev,no-proc-macro)
python=$(tree -p kairos-python -e normal,no-proc-macro)
# Every crate of the extension's build, with its features, must be one the workspace build made.
missing=$(comm -13 <(echo "$workspace") <(echo "$python") | grep -v '^kairos-python ' || true)
if [ -n "$missing" ]; then
    echo "scripts/check-python-features.sh: sdk/python resolves these crates with other features than the workspace:" >&2
    echo "$missing" | sed 's/^/  python:    /' >&2
    for crate in $(echo "$missing" | awk '{print $1}' | sort -u); do
        echo "$workspace" | grep "^$crate " | sed 's/^/  workspace: /' >&2
    done
    echo "Add the workspace's features to the feature-unification block of sdk/python/Cargo.toml." >&2
    exit 1
fi
echo "sdk/python resolves the workspace's crate features ($(echo "$python" | wc -l) crates)"
