#!/bin/bash
# On a GPU machine with the NVIDIA driver and CUDA 13.0 libraries (no Rust needed): the engine's
# CUDA tests (the whole SmolVLA pipeline's parity with LeRobot's goldens on CUDA among them) and
# the rest of its suites; then the whole SmolVLA pipeline at smolvla_base's shapes (a random
# checkpoint written here by kairos-tiny-model, two 512x512 cameras) with `kairos predict`: first
# the launch overhead at B = 1 (the `smolvla_tiny` fixture, whose compute is negligible, and
# smolvla_base in bf16, each with and without `--cuda-graphs`), then B = 1, 4, 16, 64 in f32
# and bf16 on CUDA, each run's peak GPU memory, the same pipeline on this machine's CPU with the
# fast kernels, and `kairos profile` of it on CUDA. Runs the binaries that
# scripts/build-cuda-tests.sh put in .devbin/ (as .devbin/run.sh, from the checkout's root);
# writes logs and profiles to $OUT (default /tmp/cuda-out). Sized to run in under 8 minutes.
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
if [ -x .devbin/kairos ] && [ -x .devbin/kairos-tiny-model ]; then
  # Outside $OUT: the 1.1 GB checkpoint is not a result to bring back.
  BASE=${BASE:-$(mktemp -d)/smolvla_base}
  echo "== random smolvla_base checkpoint"
  .devbin/kairos-tiny-model --preset smolvla-base --seed 0 "$BASE" | tail -1
  # One predict: the batch, the paths, every timed run's total and the stage times of the last,
  # peak host RSS and (sampled every 20 ms) peak GPU memory.
  predict() {  # label, then kairos predict arguments (the model: $MODEL, default $BASE)
    local label=$1; shift
    nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits -lms 20 > "$OUT/mem_$label.log" 2>/dev/null &
    local sampler=$!
    timeout 240 .devbin/kairos predict --model "${MODEL:-$BASE}" "$@" > "$OUT/predict_$label.json" 2> "$OUT/predict_$label.err"
    local rc=$?
    kill "$sampler" 2>/dev/null; wait "$sampler" 2>/dev/null
    python3 - "$label" "$rc" "$OUT/predict_$label.json" "$OUT/mem_$label.log" <<'P'
import json, sys
label, rc, path, mem = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4]
try:
    v = json.load(open(path))
except Exception as e:
    print(f"{label}: failed (rc {rc}): {e}"); sys.exit()
peak = max((int(l) for l in open(mem) if l.strip().isdigit()), default=0)
runs = sorted(v.get("runs_ms", []))
median = runs[len(runs) // 2] if runs else v["timing_ms"]["total"]
stages = {k: round(x, 1) for k, x in v["timing_ms"].items()}
print(f"{label}: batch {v.get('batch', 1)} median {median:.1f} ms ({median / max(v.get('batch', 1), 1):.1f} ms/robot) "
      f"runs {[round(r, 1) for r in v.get('runs_ms', [])]} stages {stages} paths {v['paths']} "
      f"peak gpu {peak} MiB, peak rss {v.get('peak_rss_mb', 0):.0f} MB")
P
  }
  echo "== launch overhead at B = 1: smolvla_tiny (negligible compute) and smolvla_base bf16, CUDA graphs off/on"
  {
    MODEL=engine/tests/fixtures/smolvla_tiny predict tiny_b1 --device cuda:0 --batch 1 --repeat 20
    MODEL=engine/tests/fixtures/smolvla_tiny predict tiny_b1_graphs --device cuda:0 --batch 1 --repeat 20 --cuda-graphs
    predict base_bf16_b1 --device cuda:0 --precision bf16 --batch 1 --repeat 10
    predict base_bf16_b1_graphs --device cuda:0 --precision bf16 --batch 1 --repeat 10 --cuda-graphs
  } | tee "$OUT/launch_overhead.txt"
  # The summary: the tiny model's time is the floor that launches and host work set; the
  # difference the graphs make to the base model's expert stage, per Euler step.
  python3 - "$OUT" engine/tests/fixtures/smolvla_tiny/config.json <<'P' | tee -a "$OUT/launch_overhead.txt"
import json, sys
out, config = sys.argv[1], sys.argv[2]
steps = json.load(open(config))["num_steps"]
def run(label):
    try:
        v = json.load(open(f"{out}/predict_{label}.json"))
    except Exception:
        return None
    runs = sorted(v["runs_ms"])
    return runs[len(runs) // 2], v["timing_ms"]["expert"]
r = {k: run(k) for k in ("tiny_b1", "tiny_b1_graphs", "base_bf16_b1", "base_bf16_b1_graphs")}
fmt = lambda x: "failed" if x is None else f"{x[0]:.2f} ms (expert {x[1]:.2f} ms)"
line = (f"launch overhead, B=1: launch-bound floor (smolvla_tiny) {fmt(r['tiny_b1'])}, with graphs "
        f"{fmt(r['tiny_b1_graphs'])}; smolvla_base bf16 {fmt(r['base_bf16_b1'])}, with graphs "
        f"{fmt(r['base_bf16_b1_graphs'])}")
for name, a, b in (("tiny", "tiny_b1", "tiny_b1_graphs"), ("base", "base_bf16_b1", "base_bf16_b1_graphs")):
    if r[a] and r[b]:
        line += f"; {name}: graphs save {(r[a][1] - r[b][1]) / steps:.3f} ms per Euler step ({steps} steps)"
print(line)
P
  echo "== full pipeline on CUDA (Candle), smolvla_base shapes, 2 cameras 512x512"
  for precision in bf16 f32; do
    for b in 1 4 16 64; do
      predict "cuda_${precision}_b$b" --device cuda:0 --precision "$precision" --batch "$b" --repeat 3
    done
  done | tee "$OUT/pipeline_cuda.txt"
  echo "== the same pipeline on this CPU (fast kernels, $(nproc) threads)"
  for precision in bf16 f32; do
    predict "cpu_${precision}_b1" --device cpu --kernels fast --threads "$(nproc)" --precision "$precision" --batch 1 --repeat 2
  done | tee "$OUT/pipeline_cpu.txt"
  echo "== profile: the whole pipeline on CUDA, bf16"
  timeout 240 .devbin/kairos profile --model "$BASE" --device cuda:0 --precision bf16 --batches 1,2,4,8,16,32,64 \
    --iterations 2 --out "$OUT/profile_cuda_bf16.json" 2>&1 | tail -12
fi
