#!/bin/bash
# Remote engine workers on loopback (docs/BENCHMARKS.md, "Remote workers"): a scheduler with no
# local engine (`kairos serve --local-engines 0`), 1 vs 2 `kairos worker` processes, 8 robots
# requesting back to back (`--trigger 0`), twice each; then a SIGKILL of one of two workers
# mid-run and when the scheduler detected the loss and re-dispatched. Usage:
#   cargo build -p kairos-cli && bash scripts/bench-workers.sh [path/to/kairos]
set -u
K=$(realpath "${1:-target/debug/kairos}")
WORK=$(mktemp -d)
trap 'kill $(jobs -p) 2>/dev/null; rm -rf "$WORK"' EXIT
cd "$WORK"
cat > profile.json <<'P'
{"model":"flow-head-small","device":"cpu (bench profile)","points":[{"batch":1,"latency_ms":30.0},{"batch":4,"latency_ms":60.0}],"max_batch":4}
P
start_serve() {
  rm -rf d; $K serve --listen 127.0.0.1:$1 --data-dir d --local-engines 0 > serve.log 2>&1 &
  SERVE=$!
  for i in $(seq 100); do [ -f d/worker-token.txt ] && grep -q "listening" serve.log && break; sleep 0.1; done
}
start_workers() {
  WORKERS=()
  for i in $(seq $1); do
    KAIROS_ENGINE_THREADS=1 $K worker --server 127.0.0.1:$2 --data-dir d --profile profile.json --worker-id w$i --max-batch 4 > w$i.log 2>&1 &
    WORKERS+=($!)
  done
  for i in $(seq 300); do [ "$(grep -c 'worker registered' serve.log)" -ge "$1" ] && break; sleep 0.1; done
}
stop_all() { kill ${WORKERS[@]} 2>/dev/null; kill -INT $SERVE 2>/dev/null; wait 2>/dev/null; }
for rep in 1 2; do
for n in 1 2; do
  port=$((15400 + n + 10*rep))
  start_serve $port; start_workers $n $port
  t0=$(date +%s.%N)
  $K robot --server 127.0.0.1:$port --data-dir d --robots 8 --rounds 10 --trigger 0 > robots-$n.log 2>&1
  t1=$(date +%s.%N)
  echo "workers=$n rep=$rep wall=$(echo "$t1 - $t0" | bc) $(grep 'rounds: asked' robots-$n.log) $(grep 'server timing' robots-$n.log)"
  stop_all
done
done
# Kill one of two workers mid-run.
port=15499
start_serve $port; start_workers 2 $port
$K robot --server 127.0.0.1:$port --data-dir d --robots 8 --rounds 10 --trigger 0 > robots-kill.log 2>&1 &
R=$!
sleep 4
echo "kill at $(date -u +%H:%M:%S.%N)"
kill -9 ${WORKERS[0]}
wait $R
grep 'rounds: asked' robots-kill.log; grep 'round latency' robots-kill.log
grep -E "batch lost|worker left" serve.log | sed 's/\x1b\[[0-9;]*m//g' | head -5
stop_all
