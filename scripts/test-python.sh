#!/usr/bin/env bash
# The Python package's tests: installs sdk/python (kairos-client, built by maturin from the
# workspace, reusing target/) and pytest into .venv, then runs sdk/python/tests against the debug
# `kairos` binary, which must be built already (scripts/test.sh builds it first).
set -euo pipefail
cd "$(dirname "$0")/.."

PYTEST_VERSION=9.2.0
[ -x .venv/bin/python ] || python3 -m venv .venv
started=$SECONDS
# Always reinstalled: the package is built from this tree. --no-deps keeps pip from reaching
# for numpy when .venv has it (scripts/test.sh installs it); a fresh venv gets it from PyPI.
if .venv/bin/python -c "import numpy" 2>/dev/null; then NO_DEPS=--no-deps; else NO_DEPS=; fi
.venv/bin/pip install --quiet --disable-pip-version-check $NO_DEPS --force-reinstall ./sdk/python
echo "[test-python.sh] pip install ./sdk/python: $((SECONDS - started)) s"
if ! .venv/bin/python -c "import pytest" 2>/dev/null; then
    .venv/bin/pip install --quiet --disable-pip-version-check "pytest==$PYTEST_VERSION"
fi
KAIROS_BIN="${KAIROS_BIN:-$PWD/target/debug/kairos}" .venv/bin/python -m pytest -q sdk/python/tests
