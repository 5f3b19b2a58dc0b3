#!/usr/bin/env bash
# Runs every test of the project. This is the README's test command and what CI (.ci/run) runs.
#
# It first installs what the tests need and cannot find in Cargo (idempotent, skipped when
# present): the plugin toolchains (Debian clang/lld/wasi-libc, componentize-py in .venv), Debian's
# chromium and prometheus, the Python packages of the cross-language client test (into the same
# .venv), and then builds the shipped WASM plugins from source (plugins/build.sh), which the plugin
# tests load.
set -euo pipefail
cd "$(dirname "$0")/.."

# Wall time of each step, so a slow CI run says where the time went (docs/BENCHMARKS.md, "CI time").
step_started=$SECONDS
step_done() {
    echo "[test.sh] $1: $((SECONDS - step_started)) s"
    step_started=$SECONDS
}

# Formatting first: it takes a second and fails before anything is built.
cargo fmt --all --check
step_done "cargo fmt --check"

bash scripts/install-plugin-toolchains.sh
# `ip` (iproute2): the remote-worker test puts a worker in a network namespace of its own
# (tests/tests/it/workers.rs, tests/src/netns.rs); it fails rather than skips without it.
if ! command -v ip >/dev/null 2>&1; then
    echo "installing iproute2 (apt)"
    SUDO=""
    if [ "$(id -u)" -ne 0 ]; then SUDO=sudo; fi
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends iproute2 >/dev/null
fi
# Debian's Chromium (the fleet page test, cli/tests/it/fleet_page.rs) and Prometheus with promtool
# (cli/tests/it/prometheus.rs and the rules check below); the tests fail rather than skip without them.
monitoring_tools=()
[ -x /usr/bin/chromium ] || monitoring_tools+=(chromium)
{ [ -x /usr/bin/prometheus ] && [ -x /usr/bin/promtool ]; } || monitoring_tools+=(prometheus)
if [ "${#monitoring_tools[@]}" -gt 0 ]; then
    echo "installing ${monitoring_tools[*]} (apt)"
    SUDO=""
    if [ "$(id -u)" -ne 0 ]; then SUDO=sudo; fi
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${monitoring_tools[@]}" >/dev/null \
        || { echo "cannot install ${monitoring_tools[*]}: install Debian's chromium and prometheus packages" >&2; exit 1; }
fi
promtool check rules deploy/monitoring/*.rules.yml
# The Python example client's packages (sdk/examples/python), for the cross-language test below.
PY_TEST_DEPS=(aioquic==1.7.2 msgpack==1.2.4 numpy==2.4.6)
if ! .venv/bin/python -c "import aioquic, msgpack, numpy" 2>/dev/null; then
    echo "installing ${PY_TEST_DEPS[*]} into .venv (pip)"
    .venv/bin/pip install --quiet --disable-pip-version-check "${PY_TEST_DEPS[@]}"
fi
# The real openpi-client from PyPI, for the openpi endpoint's tests (tests/tests/it/openpi.rs), in
# a venv of its own: it needs numpy<2, and it imports typing_extensions without declaring it.
OPENPI_DEPS=(openpi-client==0.1.2 numpy==1.26.4 websockets==17.4 msgpack==1.2.4 pillow==13.0.0 dm-tree==0.1.10 typing_extensions==4.16.0)
if ! .venv-openpi/bin/python -c "import openpi_client.websocket_client_policy" 2>/dev/null; then
    python3 -m venv .venv-openpi && .venv-openpi/bin/pip install --quiet --disable-pip-version-check "${OPENPI_DEPS[@]}"
fi
step_done "toolchains and Python packages"

# The Kubernetes manifests, validated offline (installs kubernetes-validate into .venv-k8s once):
# mostly a pip download, so it runs beside the build below and is waited for after it.
k8s_log=$(mktemp)
bash scripts/validate-k8s.sh >"$k8s_log" 2>&1 &
k8s_pid=$!

# The Python extension must resolve the workspace's features, or its pip install below compiles
# dozens of crates a second time (scripts/check-python-features.sh says which to add).
bash scripts/check-python-features.sh

# One build of the whole workspace with the test feature set; the plugins are built with the
# kairos binary it produced (the integration tests need it), so nothing compiles twice.
cargo test --workspace --locked --no-run
step_done "build (cargo test --no-run)"
k8s_status=0
wait "$k8s_pid" || k8s_status=$?
cat "$k8s_log"
rm -f "$k8s_log"
if [ "$k8s_status" -ne 0 ]; then
    echo "scripts/validate-k8s.sh failed" >&2
    exit "$k8s_status"
fi
step_done "Kubernetes manifests (ran beside the build; kubectl kustomize | kubernetes-validate --strict)"
KAIROS_BIN=target/debug/kairos bash plugins/build.sh
step_done "plugins"

# --include-ignored: the ignored tests (the Python client against the Rust responder, the real
# openpi-client against the openpi endpoint, the fleet page in Chromium, Prometheus over a live
# fleet) are ignored in a plain `cargo test` because they need the packages installed above; here
# they exist, so they run, and fail rather than skip.
# The exceptions, named here: the opt-in `real_checkpoint` tests need a real SmolVLA checkpoint
# (KAIROS_SMOLVLA_CHECKPOINT, about 1 GB, not in the repository) and `real_pi_checkpoint` a real
# π0 / π0.5 one (KAIROS_PI_CHECKPOINT, about 7 GB); each runs only when its variable is set.
real_checkpoint=()
if [ -z "${KAIROS_SMOLVLA_CHECKPOINT:-}" ]; then real_checkpoint+=(--skip real_checkpoint); fi
if [ -z "${KAIROS_PI_CHECKPOINT:-}" ]; then real_checkpoint+=(--skip real_pi_checkpoint); fi
KAIROS_PYTHON="$PWD/.venv/bin/python" KAIROS_OPENPI_PYTHON="$PWD/.venv-openpi/bin/python" cargo test --workspace --locked -- --include-ignored "${real_checkpoint[@]}"
step_done "tests"
bash scripts/test-python.sh; step_done "Python package: pip install ./sdk/python, pytest against kairos serve"
bash scripts/build-wheel.sh --profile dev
bash scripts/test-wheel.sh
step_done "Python wheel: maturin build, installed without a Rust toolchain, the LeRobot example"

# Lints last, on the tree that just passed its tests: every target of every crate, warnings as
# errors (`[workspace.lints]` and clippy.toml say which).
cargo clippy --workspace --all-targets --locked -- -D warnings
step_done "cargo clippy -D warnings"
