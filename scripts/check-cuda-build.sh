#!/usr/bin/env bash
# Compiles the `cuda` feature on a machine without a GPU or a system CUDA toolkit.
#
# NVIDIA publishes the CUDA compiler on PyPI; this script installs a pinned set of those wheels
# into .venv-cuda/ (nvcc, cicc/NVVM, the runtime and CCCL headers) and runs `cargo clippy` (a
# `cargo check` plus the lints CI applies) of the engine and the `kairos` server with
# `--features cuda`. That builds Candle's CUDA kernels with nvcc (PTX for
# every op, and the statically compiled MoE/GGUF kernels for one architecture) and type-checks
# Candle's CUDA backend and ours against them. It proves the feature compiles; it runs nothing on
# a GPU, and a machine with a GPU should still run the tests with the feature.
#
#   bash scripts/check-cuda-build.sh [extra cargo args]
#
# Environment: CUDA_COMPUTE_CAP (default 90, an H100) picks the architecture of the static
# kernels; CUDA_CHECK_TARGET_DIR (default target/cuda-check) keeps this build apart from the
# default one, whose feature set it would otherwise rebuild. Not part of scripts/test.sh: on a
# 2-core machine nvcc alone takes longer than the rest of CI.
set -euo pipefail
cd "$(dirname "$0")/.."

# CUDA 13.5 is the release whose wheels include the nvcc driver; cudarc 0.19 knows releases up
# to 13.4, whose API 13.5 keeps, so its bindings are selected as 13.4.
CUDA_WHEELS=(
    nvidia-cuda-nvcc==13.5.37
    nvidia-nvvm==13.5.37
    nvidia-cuda-crt==13.5.37
    nvidia-cuda-runtime==13.5.37
    nvidia-cuda-cccl==13.3.5.0.6
)
VENV=.venv-cuda
if [ ! -x "$VENV/bin/python" ]; then
    python3 -m venv "$VENV"
fi
if ! "$VENV/bin/pip" freeze --disable-pip-version-check 2>/dev/null | grep -q "^nvidia-cuda-nvcc==13.5.37$"; then
    echo "installing ${CUDA_WHEELS[*]} into $VENV (pip)"
    "$VENV/bin/pip" install --quiet --disable-pip-version-check --no-deps "${CUDA_WHEELS[@]}"
fi
CUDA_HOME="$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')/nvidia/cu13"
chmod +x "$CUDA_HOME"/bin/* "$CUDA_HOME"/nvvm/bin/* 2>/dev/null || true
export PATH="$CUDA_HOME/bin:$PATH" CUDA_PATH="$CUDA_HOME" CUDA_ROOT="$CUDA_HOME"
export CUDA_COMPUTE_CAP="${CUDA_COMPUTE_CAP:-90}" CUDARC_CUDA_VERSION=13040
nvcc --version | tail -2

cargo clippy --locked -p kairos-engine -p kairos-server -p kairos-cli --features cuda --all-targets \
    --target-dir "${CUDA_CHECK_TARGET_DIR:-target/cuda-check}" "$@" -- -D warnings
echo "the cuda feature compiles (nvcc $(nvcc --version | grep -o 'release [0-9.]*'), sm_$CUDA_COMPUTE_CAP)"
