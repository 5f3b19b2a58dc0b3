#!/usr/bin/env bash
# The Python client's wheel as a user installs it: target/wheels/kairos_client-*.whl
# (scripts/build-wheel.sh) into a fresh venv, by a pip that sees no Rust toolchain on PATH and may
# take only binary wheels, then the LeRobot-style example (sdk/python/examples/lerobot_robot.py)
# against a live `kairos serve` (the debug build, KAIROS_BIN). Ends with `wheel: 1 passed, 0
# failed`, or fails saying why.
set -euo pipefail
cd "$(dirname "$0")/.."

NUMPY_VERSION=2.4.6
STEPS=60
KAIROS_BIN="${KAIROS_BIN:-$PWD/target/debug/kairos}"
wheels=(target/wheels/kairos_client-*.whl)
if [ "${#wheels[@]}" -ne 1 ] || [ ! -f "${wheels[0]}" ]; then
    echo "test-wheel: build the wheel first (scripts/build-wheel.sh)" >&2
    exit 1
fi
wheel="$PWD/${wheels[0]}"
[ -x "$KAIROS_BIN" ] || { echo "test-wheel: $KAIROS_BIN missing (cargo build -p kairos-cli)" >&2; exit 1; }

work=$(mktemp -d)
server_pid=
cleanup() {
    if [ -n "$server_pid" ]; then kill "$server_pid" 2>/dev/null || true; wait "$server_pid" 2>/dev/null || true; fi
    rm -rf "$work"
}
trap cleanup EXIT

# A PATH with the venv and the system's directories only: no cargo, rustc or rustup.
python3 -m venv "$work/venv"
clean_path="$work/venv/bin:/usr/bin:/bin"
for tool in cargo rustc rustup; do
    if found=$(PATH="$clean_path" command -v "$tool"); then
        echo "test-wheel: $tool is on the clean PATH ($found)" >&2
        exit 1
    fi
done
user() { env -i HOME="$HOME" PATH="$clean_path" "$@"; }
user pip install --quiet --disable-pip-version-check --only-binary :all: \
    "$wheel" "numpy==$NUMPY_VERSION"
# The package imported is the installed one, with its compiled extension.
where=$(cd "$work" && user python -c "import kairos, kairos._kairos as k; print(k.__file__)")
case "$where" in
    "$work/venv/"*) ;;
    *) echo "test-wheel: kairos imported from $where, not from the venv" >&2; exit 1 ;;
esac

"$KAIROS_BIN" serve --listen 127.0.0.1:0 --data-dir "$work/data" >"$work/serve.log" 2>&1 &
server_pid=$!
address=
for _ in $(seq 1200); do
    address=$(sed -n 's/^ *listening on *\([^ ]*\).*/\1/p' "$work/serve.log" | head -n1)
    [ -n "$address" ] && break
    kill -0 "$server_pid" 2>/dev/null || break
    sleep 0.1
done
if [ -z "$address" ]; then
    echo "test-wheel: kairos serve did not start:" >&2
    cat "$work/serve.log" >&2
    exit 1
fi

cp sdk/python/examples/lerobot_robot.py "$work/"
out=$(cd "$work" && user python lerobot_robot.py --data-dir "$work/data" --server "$address" \
    --steps "$STEPS" --fps 100 --threshold 0.5)
echo "$out"
if echo "$out" | grep -Eq "executed $STEPS actions in [0-9]+ rounds"; then
    echo "wheel: 1 passed, 0 failed"
else
    echo "wheel: 0 passed, 1 failed (the example did not execute its $STEPS actions)" >&2
    exit 1
fi
