#!/usr/bin/env bash
# Builds the Python client (sdk/python, the `kairos-client` package) as a wheel with maturin: one
# abi3 wheel for every CPython from 3.9 on (pyo3's `abi3-py39`), into target/wheels/. Installing
# it needs no Rust toolchain: `pip install target/wheels/kairos_client-*.whl` (docs/CLIENTS.md).
#
#   scripts/build-wheel.sh [--profile release|dev] [more `maturin build` flags]
#
# release (the default) is the wheel to hand out. dev is the workspace's dev profile, whose
# dependencies are built at opt-level 3 and are already in target/ after
# `cargo test --workspace`: what CI builds to test the wheel (scripts/test-wheel.sh) without
# compiling the dependency tree a second time. maturin is installed into .venv on first use.
set -euo pipefail
cd "$(dirname "$0")/.."

MATURIN_VERSION=1.16.0
profile=release
if [ "${1:-}" = "--profile" ]; then
    profile=${2:?--profile needs release or dev}
    shift 2
fi
[ -x .venv/bin/python ] || python3 -m venv .venv
if ! .venv/bin/maturin --version 2>/dev/null | grep -qx "maturin $MATURIN_VERSION"; then
    echo "installing maturin==$MATURIN_VERSION into .venv (pip)"
    .venv/bin/pip install --quiet --disable-pip-version-check "maturin==$MATURIN_VERSION"
fi
rm -f target/wheels/kairos_client-*.whl
.venv/bin/maturin build --quiet --manifest-path sdk/python/Cargo.toml --profile "$profile" \
    --out target/wheels "$@"
wheels=(target/wheels/kairos_client-*.whl)
if [ "${#wheels[@]}" -ne 1 ] || [ ! -f "${wheels[0]}" ]; then
    echo "build-wheel: expected one wheel in target/wheels, found: ${wheels[*]}" >&2
    exit 1
fi
case "${wheels[0]}" in
    *-abi3-*) ;;
    *) echo "build-wheel: ${wheels[0]} is not an abi3 wheel" >&2; exit 1 ;;
esac
echo "${wheels[0]}"
