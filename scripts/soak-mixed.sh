# The mixed soak of scripts/soak.sh (`--mixed`), sourced by it after its set-up: $bin, $root,
# $work, $minutes, $baseline_minutes, $robots, $rounds, $hz, $stagger, $other_pids, $robot_pids,
# $server_pid, $sampler_pid, and its functions account and rss_kib. See soak.sh's header for
# what it runs and the verdict; docs/RELIABILITY.md, "Mixed soak", for the recorded runs.

tools=${KAIROS_TOOLS:-$(dirname "$bin")}
python=${KAIROS_OPENPI_PYTHON:-$root/.venv-openpi/bin/python}
openpi_clients=${OPENPI_CLIENTS:-3}
openpi_period=${OPENPI_PERIOD_S:-1}
openpi_calls=${OPENPI_CALLS:-30}
max_connections=${MAX_CONNECTIONS:-96}
quic_slots=${QUIC_SLOTS:-64}
tcp_slots=${TCP_SLOTS:-64}
# The attackers' own address: the per-address guards (handshake places per source) cannot tell
# clients on one address apart before they authenticate, so on one loopback address a slowloris
# holding that address's share of the openpi door's handshake places shuts out the well-behaved
# openpi clients too. Empty: the attackers share 127.0.0.1 with the clients.
attack_source=${ATTACK_SOURCE-127.0.0.2}
# The attackers' CPU priority. On a network an attacker's loop runs on its own machine; here it
# shares the server's cores, and a connect flood that reconnects the instant it is refused spends
# as much CPU on its own side as the server spends refusing it. At the lowest priority the
# attackers still take every cycle the server and the well-behaved clients leave idle, and the
# server's work to refuse them stays in the measurement; their own loop's does not. 0: equal
# priority (the attackers' own CPU counts against the server too).
attack_nice=${ATTACK_NICE-19}

for tool in "$tools/kairos-attack" "$tools/kairos-hostile-worker"; do
    if [ ! -x "$tool" ]; then
        echo "missing $tool: cargo build -p kairos-tests --bins (or set KAIROS_TOOLS)" >&2
        exit 1
    fi
done
if ! "$python" -c "import openpi_client.websocket_client_policy" 2>/dev/null; then
    echo "no openpi-client in $python: set KAIROS_OPENPI_PYTHON (scripts/test.sh makes .venv-openpi)" >&2
    exit 1
fi

free_tcp_port() {
    python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'
}

new_token() {
    python3 -c 'import secrets; print("kairos_" + secrets.token_hex(24))'
}

sha256() {
    printf %s "$1" | sha256sum | cut -d' ' -f1
}

# Waits up to $3 seconds for the pattern $2 in the file $1 while the process $4 lives.
wait_for_line() {
    local i
    for i in $(seq 1 $(($3 * 10))); do
        if grep -q "$2" "$1" 2>/dev/null; then
            return 0
        fi
        if ! kill -0 "$4" 2>/dev/null; then
            echo "pid $4 exited before \"$2\" in $1:" >&2
            tail -20 "$1" >&2
            exit 1
        fi
        sleep 0.1
    done
    echo "no \"$2\" in $1 within $3 s" >&2
    exit 1
}

# One `kairos robot` fleet on token $fleet_token, recorded to $3; its report goes to $2.
mixed_fleet() {
    exec "$bin" robot --server "$quic" --data-dir "$data" --token "$fleet_token" --robots "$1" \
        --rounds "$rounds" --control-hz "$hz" --image 32x32 --stagger-ms "$stagger" \
        --record "$3" >"$2" 2>&1
}

# p50, p99 and max (ms) of the round trips of every round in the trace files given.
trace_latency() {
    python3 - "$@" <<'EOF'
import json, sys
values = []
for path in sys.argv[1:]:
    with open(path) as f:
        for line in list(f)[1:]:
            if line.strip():
                values += [r["round_trip_us"] / 1e3 for r in json.loads(line)["rounds"] if "round_trip_us" in r]
def percentile(q):
    # Linear interpolation between closest ranks: numpy's default, the project's definition.
    s = sorted(values)
    k = (len(s) - 1) * q
    lo = int(k)
    hi = min(lo + 1, len(s) - 1)
    return s[lo] + (s[hi] - s[lo]) * (k - lo)
print("%.1f %.1f %.1f %d" % (percentile(0.5), percentile(0.99), max(values), len(values)) if values else "nan nan nan 0")
EOF
}

# The sum of the samples of the metric family $2 in the scrape $1 whose labels contain $3.
metric_sum() {
    awk -v family="$2" -v labels="$3" '
        index($0, family "{") == 1 && index($0, labels) > 0 { sum += $NF }
        END { print sum + 0 }' "$1"
}

# One run: $1 its name, $2 1 with attackers (0 without), $3 minutes. Leaves its numbers in
# $work/$1/result as `key value` lines.
mixed_run() {
    local name=$1 attackers=$2 run_minutes=$3
    local dir="$work/$name"
    mkdir -p "$dir"
    data="$dir/data"
    quic="127.0.0.1:$(python3 -c 'import socket; s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')"
    local openpi="127.0.0.1:$(free_tcp_port)" metrics="127.0.0.1:$(free_tcp_port)"
    fleet_token=$(new_token)
    local openpi_token hog_token
    openpi_token=$(new_token)
    hog_token=$(new_token)
    cat >"$dir/kairos.toml" <<EOF
[[robot]]
name = "fleet"
token_sha256 = "$(sha256 "$fleet_token")"

[[robot]]
name = "openpi"
token_sha256 = "$(sha256 "$openpi_token")"

[[robot]]
name = "hog"
token_sha256 = "$(sha256 "$hog_token")"

[connections]
max_connections = $max_connections
EOF
    echo
    echo "== $name: $run_minutes min, $([ "$attackers" = 1 ] && echo with || echo without) attackers; QUIC $quic, openpi $openpi, metrics $metrics =="
    "$bin" serve --config "$dir/kairos.toml" --data-dir "$data" --listen "$quic" \
        --local-engines 0 --openpi-listen "$openpi" --metrics-listen "$metrics" \
        >"$dir/server.log" 2>&1 &
    server_pid=$!
    wait_for_line "$dir/server.log" "listening on" 120 "$server_pid"
    "$bin" worker --server "$quic" --data-dir "$data" --model builtin --worker-id healthy \
        >"$dir/worker.log" 2>&1 &
    local worker_pid=$!
    other_pids+=("$worker_pid")
    wait_for_line "$dir/worker.log" "registered" 300 "$worker_pid"
    echo "server pid $server_pid; healthy worker pid $worker_pid registered"
    local attack_pid="" hostile_pid=""
    if [ "$attackers" = 1 ]; then
        nice -n "$attack_nice" "$tools/kairos-hostile-worker" --server "$quic" --data-dir "$data" >"$dir/hostile.log" 2>&1 &
        hostile_pid=$!
        nice -n "$attack_nice" "$tools/kairos-attack" --server "$quic" --data-dir "$data" --openpi "$openpi" \
            --metrics "$metrics" --hog-token "$hog_token" --quic-slots "$quic_slots" \
            --tcp-slots "$tcp_slots" ${attack_source:+--source-ip "$attack_source"} \
            >"$dir/attack.log" 2>&1 &
        attack_pid=$!
        other_pids+=("$hostile_pid" "$attack_pid")
        # The attackers take their places before the well-behaved load starts.
        sleep 10
        echo "attackers: hostile worker pid $hostile_pid, kairos-attack pid $attack_pid"
    fi

    local t0 deadline
    t0=$(date +%s)
    deadline=$((t0 + run_minutes * 60))
    (
        while kill -0 "$server_pid" 2>/dev/null; do
            echo "$(($(date +%s) - t0)) $(rss_kib "$server_pid")"
            sleep 10
        done
    ) >"$dir/rss.tsv" &
    sampler_pid=$!
    "$python" "$root/tests/python/openpi_soak.py" "${openpi%:*}" "${openpi##*:}" "$openpi_token" \
        "$openpi_clients" $((run_minutes * 60)) "$openpi_period" "$openpi_calls" \
        >"$dir/openpi.json" 2>"$dir/openpi.log" &
    local openpi_pid=$!
    other_pids+=("$openpi_pid")

    local totals=(0 0 0 0 0 0) fleets=0 robot_errors=0 log counts errors i
    while [ "$(date +%s)" -lt "$deadline" ]; do
        fleets=$((fleets + 1))
        log="$dir/fleet.$fleets.log"
        mixed_fleet "$robots" "$log" "$dir/fleet.$fleets.trace" &
        robot_pids=($!)
        wait "${robot_pids[0]}" || true
        robot_pids=()
        read -r -a counts <<<"$(account "$log" $((robots * rounds)))"
        for i in 0 1 2 3 4 5; do
            totals[i]=$((totals[i] + counts[i]))
        done
        errors=$(sed -n 's/^\([0-9]*\) of [0-9]* robots failed:.*/\1/p' "$log")
        robot_errors=$((robot_errors + ${errors:-0}))
        echo "fleet $fleets at $(($(date +%s) - t0)) s: $(grep -m1 '^rounds: asked' "$log" || echo 'no report (see log)'), server RSS $(($(rss_kib "$server_pid") / 1024)) MiB"
    done
    wait "$openpi_pid" || true
    local elapsed=$(($(date +%s) - t0))
    # The server's own counters, while the attackers still run (the metrics door is attacked).
    curl -s --max-time 30 "http://$metrics/metrics" >"$dir/metrics.txt" || echo "(the /metrics scrape failed)"
    local pid
    for pid in $attack_pid $hostile_pid; do
        kill -TERM "$pid" 2>/dev/null || true
        wait "$pid" 2>/dev/null || true
    done
    kill -TERM "$worker_pid" 2>/dev/null || true
    wait "$worker_pid" 2>/dev/null || true
    other_pids=()
    kill -INT "$server_pid"
    wait "$server_pid" || true
    server_pid=""
    kill "$sampler_pid" 2>/dev/null || true
    wait "$sampler_pid" 2>/dev/null || true
    sampler_pid=""

    local replies
    replies=$(sed -n 's/^stopped: [0-9]* connections ([0-9]* openpi), \([0-9]*\) rounds answered.*/\1/p' "$dir/server.log")
    local robot_latency openpi_numbers
    robot_latency=$(trace_latency "$dir"/fleet.*.trace)
    openpi_numbers=$(python3 - "$dir/openpi.json" <<'EOF'
import json, sys
try:
    r = json.load(open(sys.argv[1]))
except Exception:
    print("0 0 0 0 0 0 0 nan nan nan")
    sys.exit()
l = r["latency"]
fmt = lambda v: "nan" if v is None else "%.1f" % v
print(r["answered"], r["failed"], r["hung"] + r["hung_connecting"], r["duplicates"], r["out_of_order"],
      r["connects"], r["connect_failures"], fmt(l["p50_ms"]), fmt(l["p99_ms"]), fmt(l["max_ms"]))
EOF
)
    local o_answered o_failed o_hung o_dup o_order o_connects o_connect_failed o_p50 o_p99 o_max
    read -r o_answered o_failed o_hung o_dup o_order o_connects o_connect_failed o_p50 o_p99 o_max <<<"$openpi_numbers"
    local r_p50 r_p99 r_max r_n
    read -r r_p50 r_p99 r_max r_n <<<"$robot_latency"
    local base_t base last_t last
    read -r base_t base <<<"$(awk -v m="$run_minutes" '$2 > 0 && (m < 3 || $1 >= 120) { print $1, $2; exit }' "$dir/rss.tsv")"
    read -r last_t last <<<"$(awk '$2 > 0 { t = $1; r = $2 } END { print t, r }' "$dir/rss.tsv")"

    echo "-- $name: $elapsed s --"
    echo "robots:  $robots x $fleets fleets of $rounds rounds at $hz Hz: asked ${totals[0]}, answered ${totals[1]}, lost ${totals[2]}, answered twice ${totals[3]}, retried ${totals[4]}, tasks not ended ${totals[5]}, robots failed $robot_errors; round latency p50 $r_p50 ms, p99 $r_p99 ms, max $r_max ms ($r_n rounds)"
    echo "openpi:  $openpi_clients clients: answered $o_answered, failed $o_failed, hung $o_hung, duplicates $o_dup, out of order $o_order; connects $o_connects, failed connects $o_connect_failed; latency p50 $o_p50 ms, p99 $o_p99 ms, max $o_max ms"
    if grep -q '"errors": \[\]' "$dir/openpi.json" 2>/dev/null; then :; else
        python3 -c 'import json,sys; [print("  openpi error:", e) for e in json.load(open(sys.argv[1])).get("errors", [])[:5]]' "$dir/openpi.json" 2>/dev/null || true
    fi
    echo "server:  ${replies:-?} replies; robots + openpi received $((totals[1] + o_answered))"
    grep -A1 '^stopped:' "$dir/server.log" | sed 's/^/  /' || true
    echo "rss (KiB, every 10 s): $(awk '{ printf "%s ", $2 }' "$dir/rss.tsv")"
    echo "rss: ${base} KiB at ${base_t} s, ${last} KiB at ${last_t} s"
    if [ "$attackers" = 1 ]; then
        sed 's/^/attack:  /' "$dir/attack.log" | tail -4
        sed 's/^/attack:  /' "$dir/hostile.log" | grep 'hostile worker:' || true
    fi
    echo "refusals (kairos_refusals_total, non-zero):"
    grep '^kairos_refusals_total{' "$dir/metrics.txt" | awk '$NF != 0 { print "  " $0 }' || true
    echo "workers removed (kairos_worker_removed_total, non-zero):"
    grep '^kairos_worker_removed_total{' "$dir/metrics.txt" | awk '$NF != 0 { print "  " $0 }' || true
    {
        echo "lost ${totals[2]}"
        echo "twice ${totals[3]}"
        echo "openpi_lost $((o_failed + o_hung + o_connect_failed))"
        echo "openpi_duplicates $((o_dup + o_order))"
        echo "replies ${replies:-x}"
        echo "received $((totals[1] + o_answered))"
        echo "robot_p99 $r_p99"
        echo "openpi_p99 $o_p99"
        echo "rss_base $base"
        echo "rss_last $last"
        echo "refusals $(metric_sum "$dir/metrics.txt" kairos_refusals_total '')"
        echo "removed $(metric_sum "$dir/metrics.txt" kairos_worker_removed_total '')"
    } >"$dir/result"
}

result() {
    awk -v key="$2" '$1 == key { print $2 }' "$work/$1/result"
}

mixed_run attacked 1 "$minutes"
if [ "$baseline_minutes" -gt 0 ]; then
    mixed_run baseline 0 "$baseline_minutes"
fi

echo
echo "== mixed soak: $minutes min with attackers$([ "$baseline_minutes" -gt 0 ] && echo ", baseline $baseline_minutes min without") =="
verdict=PASS
fail() {
    echo "FAIL: $*"
    verdict=FAIL
}
[ "$(result attacked lost)" = 0 ] || fail "robots lost $(result attacked lost) rounds (robots that failed count all theirs)"
[ "$(result attacked twice)" = 0 ] || fail "robots got $(result attacked twice) rounds answered twice"
[ "$(result attacked openpi_lost)" = 0 ] || fail "openpi clients lost $(result attacked openpi_lost) calls (failed, hung or failed connects)"
[ "$(result attacked openpi_duplicates)" = 0 ] || fail "openpi clients got $(result attacked openpi_duplicates) duplicate or out-of-order answers"
[ "$(result attacked replies)" = "$(result attacked received)" ] ||
    fail "the server sent $(result attacked replies) replies; robots and openpi clients received $(result attacked received)"
rss_base=$(result attacked rss_base)
rss_last=$(result attacked rss_last)
growth=$(awk -v a="$rss_base" -v b="$rss_last" 'BEGIN { printf "%.1f", (b - a) * 100 / a }')
if awk -v a="$rss_base" -v b="$rss_last" 'BEGIN { exit !(b > a * 1.10 || b < a * 0.90) }'; then
    fail "memory not flat: ${growth}%"
else
    echo "memory flat: ${growth}% (within 10%)"
fi
if [ "$baseline_minutes" -gt 0 ]; then
    for what in robot openpi; do
        with=$(result attacked "${what}_p99")
        without=$(result baseline "${what}_p99")
        ratio=$(awk -v a="$with" -v b="$without" 'BEGIN { if (b > 0) printf "%.2f", a / b; else print "nan" }')
        echo "$what p99: $with ms with attackers, $without ms without: ${ratio}x"
        awk -v r="$ratio" 'BEGIN { exit !(r != "nan" && r <= 2.0) }' || fail "$what p99 is ${ratio}x the baseline's (limit 2x)"
    done
else
    echo "p99 not compared (no baseline run)"
fi
[ "$(result attacked refusals)" != 0 ] || echo "note: the server counted no refusal (kairos_refusals_total)"
[ "$(result attacked removed)" != 0 ] || echo "note: the server removed no worker (kairos_worker_removed_total)"
echo "verdict: $verdict"
[ "$verdict" = PASS ]
