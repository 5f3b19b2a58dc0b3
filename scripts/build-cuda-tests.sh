#!/usr/bin/env bash
# Builds the engine's CUDA tests and a CUDA `kairos` here, on a machine without a GPU or a CUDA
# toolkit, for a GPU machine that has the NVIDIA driver and CUDA 13.0 libraries but no Rust
# (the lent H100/H200 machines: `scripts/run-cuda-tests.sh` runs them there).
#
#   bash scripts/build-cuda-tests.sh        # -> .devbin/{it,unit,kairos,kairos-tiny-model}.xz
#                                           #    and run-cuda-tests.sh
#
# Why not scripts/check-cuda-build.sh's toolchain: that one is CUDA 13.5 (it only type-checks).
# A binary that runs must match the GPU machine's driver: PTX from nvcc 13.5 is newer than a
# CUDA 13.0 driver (580.x) can load, and `cudarc`'s 13.4 bindings could name functions its
# libraries lack. So this installs NVIDIA's CUDA 13.0 wheels (nvcc, cuBLAS, cuRAND, NVRTC) into
# `.venv-cuda130/` and builds with `CUDARC_CUDA_VERSION=13000`.
#
# Candle links `libcuda` (the driver) at build time, which no wheel ships: `.cuda-link/` gets a
# stub `libcuda.so` (soname `libcuda.so.1`) exporting every `cu*` function that cudarc 0.19
# declares, so the link succeeds; at run time the driver's real `libcuda.so.1` is loaded instead.
# The test binaries find their fixtures through the path they were built at (`CARGO_MANIFEST_DIR`),
# so run-cuda-tests.sh links that path to its checkout.
set -euo pipefail
cd "$(dirname "$0")/.."
WHEELS=(
    nvidia-cuda-nvcc==13.0.88 nvidia-nvvm==13.0.88 nvidia-cuda-crt==13.0.88
    nvidia-cuda-runtime==13.0.96 nvidia-cuda-cccl==13.0.85 nvidia-curand==10.4.0.35
    nvidia-cuda-nvrtc==13.0.88 'nvidia-cublas==13.0.*'
)
VENV=.venv-cuda130
[ -x "$VENV/bin/python" ] || python3 -m venv "$VENV"
if ! "$VENV/bin/pip" freeze --disable-pip-version-check 2>/dev/null | grep -q "^nvidia-cuda-nvcc==13.0.88$"; then
    echo "installing the CUDA 13.0 wheels into $VENV (pip)"
    "$VENV/bin/pip" install --quiet --disable-pip-version-check --no-deps "${WHEELS[@]}"
fi
CUDA_HOME="$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')/nvidia/cu13"
chmod +x "$CUDA_HOME"/bin/* "$CUDA_HOME"/nvvm/bin/* 2>/dev/null || true

# Link directory: unversioned names for the wheels' libraries, and the libcuda stub.
LINK=$PWD/.cuda-link
mkdir -p "$LINK"
for lib in cublas cublasLt curand nvrtc cudart; do
    ln -sf "$(ls "$CUDA_HOME"/lib/lib$lib.so.* | head -1)" "$LINK/lib$lib.so"
done
CUDARC=$(cargo metadata --format-version 1 --locked --all-features | python3 -c \
    'import json,sys; print(next(p["manifest_path"] for p in json.load(sys.stdin)["packages"] if p["name"]=="cudarc").rsplit("/",1)[0])')
grep -oE "fn (cu[A-Za-z0-9_]+)\(" "$CUDARC/src/driver/sys/mod.rs" | sed -E 's/fn (.*)\(/\1/' | sort -u \
    | awk '{print "void "$1"(void){}"}' > "$LINK/stub.c"
cc -shared -fPIC -Wl,-soname,libcuda.so.1 -o "$LINK/libcuda.so" "$LINK/stub.c"

export PATH="$CUDA_HOME/bin:$PATH" CUDA_PATH="$CUDA_HOME" CUDA_ROOT="$CUDA_HOME" CUDA_HOME
export CUDA_COMPUTE_CAP="${CUDA_COMPUTE_CAP:-90}" CUDARC_CUDA_VERSION=13000
export RUSTFLAGS="-L native=$LINK" CARGO_TARGET_DIR=target/cuda-gpu
mkdir -p "$CARGO_TARGET_DIR"
nvcc --version | tail -2
cargo test --locked -p kairos-engine --features cuda --no-run --message-format json 2>/dev/null \
    | python3 -c 'import json,sys
for line in sys.stdin:
    m = json.loads(line)
    if m.get("reason") == "compiler-artifact" and m.get("executable") and m["target"]["name"] in ("kairos_engine", "it"):
        print(m["target"]["name"], m["executable"])' > target/cuda-gpu/test-binaries.txt
cargo build --locked -p kairos-cli --bin kairos --features cuda
# The random smolvla_base writer: the GPU machine has no checkpoint and no network.
cargo build --locked -p kairos-tests --bin kairos-tiny-model

mkdir -p .devbin
while read -r name exe; do
    out=.devbin/$([ "$name" = it ] && echo it || echo unit)
    strip -o "$out" "$exe" && xz -T2 -6 -f "$out"
done < target/cuda-gpu/test-binaries.txt
strip -o .devbin/kairos target/cuda-gpu/debug/kairos && xz -T2 -6 -f .devbin/kairos
strip -o .devbin/kairos-tiny-model target/cuda-gpu/debug/kairos-tiny-model \
    && xz -T2 -6 -f .devbin/kairos-tiny-model
cp scripts/run-cuda-tests.sh .devbin/run.sh
echo "$PWD" > .devbin/built-at
ls -la .devbin
echo "built; on the GPU machine, from this checkout's root: bash .devbin/run.sh (carry .devbin)"
