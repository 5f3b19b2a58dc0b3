#!/usr/bin/env bash
# Installs what plugins/build.sh needs to build the shipped policy plugins from source:
#   - C:      Debian clang, lld, wasi-libc and the wasm32 compiler-rt builtins (apt);
#   - Python: componentize-py, into the repository's .venv (pip).
# Idempotent: skips what is already there. The server itself needs none of this.
set -euo pipefail
cd "$(dirname "$0")/.."

COMPONENTIZE_PY_VERSION=0.25.1

have_c_toolchain() {
    command -v clang >/dev/null 2>&1 && command -v wasm-ld >/dev/null 2>&1 &&
        [ -e /usr/include/wasm32-wasi/stdlib.h ] &&
        [ -e "$(clang --target=wasm32-wasi -print-resource-dir)/lib/wasi/libclang_rt.builtins-wasm32.a" ]
}

if ! have_c_toolchain; then
    echo "installing clang, lld, wasi-libc, wasm32 compiler-rt (apt)"
    SUDO=""
    if [ "$(id -u)" -ne 0 ]; then SUDO=sudo; fi
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends \
        clang lld wasi-libc libclang-rt-dev-wasm32 >/dev/null
    have_c_toolchain || { echo "C/wasm32 toolchain still incomplete after apt-get" >&2; exit 1; }
fi

if ! [ -x .venv/bin/componentize-py ] ||
    [ "$(.venv/bin/componentize-py --version 2>/dev/null)" != "componentize-py $COMPONENTIZE_PY_VERSION" ]; then
    echo "installing componentize-py $COMPONENTIZE_PY_VERSION into .venv (pip)"
    python3 -m venv .venv
    .venv/bin/pip install --quiet --disable-pip-version-check "componentize-py==$COMPONENTIZE_PY_VERSION"
fi

echo "plugin toolchains: $(clang --version | head -n1); $(.venv/bin/componentize-py --version)"
