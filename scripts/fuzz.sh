#!/usr/bin/env bash
# Coverage-guided fuzzing of every parser a stranger feeds (docs/RELIABILITY.md, "6. Fuzzing"),
# on the stable toolchain with afl.rs (AFL++ 4.x, built from the `afl` crate's bundled source).
#
#   scripts/fuzz.sh [SECONDS] [TARGET...]
#
# SECONDS per target (default 600); TARGET is any of wire trace config plugin_params image http
# (default all). `scripts/fuzz.sh 20` is the quick look. FUZZ_JOBS=N runs N targets at once
# (default 1). Findings stay in tests/fuzz/out/<target>/default/{crashes,hangs}; a crash input
# becomes a regression file in tests/fuzz/regressions/<target>/ once its bug is fixed, and the
# replay test (`cargo test -p kairos-tests --test it fuzz_replay`) runs it on every CI run.
# The 10-minute runs are not part of CI.
set -euo pipefail

seconds=${1:-600}
shift || true
targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
    targets=(wire trace config plugin_params image http)
fi
jobs=${FUZZ_JOBS:-1}

root=$(cd "$(dirname "$0")/.." && pwd)
fuzz="$root/tests/fuzz"
cd "$fuzz"

if ! cargo afl --version >/dev/null 2>&1; then
    echo "== installing cargo-afl (crates.io) =="
    cargo install cargo-afl --version '^0.18' --locked
fi
# Builds AFL++ once per rustc version; says so and does nothing when it is already built.
cargo afl config --build >/dev/null 2>&1 || true

echo "== building the instrumented fuzz binary (cargo afl build --release) =="
AFL_OPT_LEVEL=${AFL_OPT_LEVEL:-1} cargo afl build --release
bin="$fuzz/target/release/kairos-fuzz"

# A shared or containerised machine: no CPU binding, no frequency or core-pattern checks.
export AFL_NO_UI=1 AFL_NO_AFFINITY=1 AFL_SKIP_CPUFREQ=1 AFL_AUTORESUME=1
export AFL_I_DONT_CARE_ABOUT_MISSING_CRASHES=1 AFL_SKIP_CRASHES=1

run_target() {
    local target=$1
    mkdir -p "out/$target"
    echo "== $target: ${seconds}s =="
    # -V: stop after this many seconds; -t: an input running over 1 s is a hang.
    cargo afl fuzz -V "$seconds" -t 1000 -i "corpus/$target" -o "out/$target" \
        "$bin" "$target" >"out/$target/fuzz.log" 2>&1 || {
        echo "afl-fuzz failed for $target; see tests/fuzz/out/$target/fuzz.log" >&2
        tail -20 "out/$target/fuzz.log" >&2
        return 1
    }
}

running=0
status=0
for target in "${targets[@]}"; do
    run_target "$target" &
    running=$((running + 1))
    if [ "$running" -ge "$jobs" ]; then
        wait -n || status=1
        running=$((running - 1))
    fi
done
while [ "$running" -gt 0 ]; do
    wait -n || status=1
    running=$((running - 1))
done

echo
printf '%-14s %8s %12s %10s %10s %14s %8s %8s %7s\n' target run_s execs execs/s corpus edges bitmap crashes hangs
findings=0
for target in "${targets[@]}"; do
    stats="out/$target/default/fuzzer_stats"
    if [ ! -f "$stats" ]; then
        printf '%-14s no stats (did afl-fuzz start?)\n' "$target"
        status=1
        continue
    fi
    get() { awk -F' *: *' -v k="$1" '$1 == k { print $2 }' "$stats"; }
    crashes=$(get saved_crashes)
    hangs=$(get saved_hangs)
    findings=$((findings + crashes + hangs))
    printf '%-14s %8s %12s %10s %10s %14s %8s %8s %7s\n' "$target" "$(get run_time)" \
        "$(get execs_done)" "$(get execs_per_sec)" "$(get corpus_count)" \
        "$(get edges_found)/$(get total_edges)" "$(get bitmap_cvg)" "$crashes" "$hangs"
done
if [ "$findings" -gt 0 ]; then
    echo "findings: tests/fuzz/out/<target>/default/{crashes,hangs}/ (replay one with: $bin TARGET < FILE)"
fi
exit "$status"
