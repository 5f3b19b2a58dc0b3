#!/bin/bash
# On a GPU machine with the NVIDIA driver and CUDA 13.0 libraries (no Rust needed): the engine's
# CUDA tests and the rest of its suites, then `kairos profile` of the SmolVLA expert on CUDA and
# on this machine's CPU. Runs the binaries that scripts/build-cuda-tests.sh put in .devbin/
# (as .devbin/run.sh, from the checkout's root); writes logs and profiles to $OUT (default /tmp/cuda-out).
#
# examples_help::the_timing_examples_answer_help_with_their_usage fails here by design: it runs
# the engine's example binaries, which are not carried.
cd "$(dirname "$0")/.."
OUT=${OUT:-/tmp/cuda-out}; mkdir -p "$OUT"
echo "== machine"; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
grep -m1 "model name" /proc/cpuinfo; nproc
grep -m1 flags /proc/cpuinfo | tr ' ' '\n' | grep -E "^(avx2|fma|avx512f|avx512_bf16|avx512_vnni|amx_bf16)$" | paste -sd' '
for f in .devbin/*.xz; do python3 -c "import lzma,sys; open(sys.argv[2],'wb').write(lzma.open(sys.argv[1]).read())" "$f" "${f%.xz}"; chmod +x "${f%.xz}"; done
libs=$(python3 - <<'P'
import glob, os
d = set(os.path.dirname(p) for pat in ("libcublas.so.13", "libcurand.so.10", "libcudart.so.13") for p in glob.glob("/opt/**/" + pat, recursive=True) + glob.glob("/usr/**/" + pat, recursive=True))
print(":".join(sorted(d)))
P
)
export LD_LIBRARY_PATH="$libs:/usr/local/nvidia/lib64:/usr/local/nvidia/lib:$LD_LIBRARY_PATH"
echo "LD_LIBRARY_PATH=$LD_LIBRARY_PATH"
ldd .devbin/it | grep -E "cuda|cublas|curand|not found"
# The test binaries find their fixtures through the manifest path they were built with.
built_at=$(cat .devbin/built-at)
if [ "$built_at" != "$PWD" ]; then mkdir -p "$(dirname "$built_at")" && ln -sfn "$PWD" "$built_at"; fi
echo "== CUDA tests"
.devbin/it cuda --test-threads 1 2>&1 | tee $OUT/cuda_tests.log | tail -20
echo "== all engine integration tests (this CPU)"
.devbin/it --test-threads 8 2>&1 | tee $OUT/it.log | tail -6
echo "== engine unit tests (this CPU)"
.devbin/unit --test-threads 8 2>&1 | tee $OUT/unit.log | tail -6
if [ -x .devbin/kairos ]; then
  echo "== profile: SmolVLA expert (random weights), CUDA vs this CPU"
  .devbin/kairos profile --model builtin:smolvla-random --device cuda:0 --batches 1,4,16,64 --iterations 5 --out $OUT/profile_cuda.json 2>&1 | tail -12
  .devbin/kairos profile --model builtin:smolvla-random --device cpu --kernels fast --threads 16 --batches 1,4,16,64 --iterations 3 --out $OUT/profile_cpu16.json 2>&1 | tail -12
  nvidia-smi --query-gpu=memory.used --format=csv,noheader
fi
