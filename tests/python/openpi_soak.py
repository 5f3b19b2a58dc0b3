"""Well-behaved openpi clients for the mixed soak (scripts/soak.sh --mixed).

Each of CLIENTS threads connects with the unmodified openpi-client from PyPI
(`WebsocketClientPolicy`), calls `infer` once every PERIOD seconds, and reconnects after
CALLS_PER_CONNECTION calls (so new connections are made all along, as robots restarting would),
until SECONDS have passed. Usage:

    openpi_soak.py HOST PORT KEY CLIENTS SECONDS PERIOD CALLS_PER_CONNECTION

Counted per call: answered (with its latency), failed (an exception: an error text from the
server, a closed connection), and duplicates or out-of-order answers (the reply's `kairos.round`
is not the connection's next round, or its `kairos.task` not the connection's task). Counted per
connect: connects and failed connects (a refusal, or no answer within websockets' 10 s open
timeout). A call or a connect (the metadata message has no timeout) still waiting 60 s after
the end is counted as hung. Prints one JSON object.
"""

import json
import sys
import threading
import time

import numpy as np
from openpi_client import websocket_client_policy

# A call still in flight this long after the end is hung (a server that never answers).
HANG_AFTER_S = 60.0


def observation(metadata, rng):
    """A LIBERO-shaped observation for the served model's shapes."""
    return {
        "observation/image": rng.integers(0, 256, (32, 32, 3), dtype=np.uint8),
        "observation/wrist_image": rng.integers(0, 256, (32, 32, 3), dtype=np.uint8),
        "observation/state": rng.uniform(-0.2, 0.2, metadata["state_dim"]),
        "prompt": "put the bowl on the plate",
    }


class Counts:
    def __init__(self):
        self.lock = threading.Lock()
        self.latencies_ms = []
        self.failed = 0
        self.duplicates = 0
        self.out_of_order = 0
        self.connects = 0
        self.connect_failures = 0
        self.in_flight = 0
        self.connecting = 0
        self.errors = []

    def add(self, **changes):
        with self.lock:
            for name, delta in changes.items():
                setattr(self, name, getattr(self, name) + delta)

    def error(self, what, e):
        with self.lock:
            if len(self.errors) < 20:
                self.errors.append(f"{what}: {e!r}"[:300])


def client(index, host, port, key, deadline, period, per_connection, counts):
    rng = np.random.default_rng(index)
    while time.monotonic() < deadline:
        counts.add(connecting=1)
        try:
            policy = websocket_client_policy.WebsocketClientPolicy(host, port, api_key=key)
        except Exception as e:  # a refusal or a timeout: counted, then tried again
            counts.add(connecting=-1, connect_failures=1)
            counts.error("connect", e)
            time.sleep(1.0)
            continue
        counts.add(connecting=-1, connects=1)
        metadata = policy.get_server_metadata()
        task = metadata.get("task")
        seen = set()
        for expected in range(per_connection):
            if time.monotonic() >= deadline:
                break
            started = time.monotonic()
            counts.add(in_flight=1)
            try:
                reply = policy.infer(observation(metadata, rng))
            except Exception as e:
                counts.add(in_flight=-1, failed=1)
                counts.error("infer", e)
                break
            ms = (time.monotonic() - started) * 1e3
            counts.add(in_flight=-1)
            kairos = reply.get("kairos", {})
            answered_round = kairos.get("round")
            if answered_round in seen or kairos.get("task") != task:
                counts.add(duplicates=1)
            elif answered_round != expected:
                counts.add(out_of_order=1)
            seen.add(answered_round)
            with counts.lock:
                counts.latencies_ms.append(ms)
            time.sleep(max(0.0, period - (time.monotonic() - started)))
        try:
            policy._ws.close()
        except Exception:
            pass


def main():
    host, port, key = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    clients, seconds = int(sys.argv[4]), float(sys.argv[5])
    period, per_connection = float(sys.argv[6]), int(sys.argv[7])
    deadline = time.monotonic() + seconds
    counts = Counts()
    threads = [
        threading.Thread(
            target=client,
            args=(i, host, port, key, deadline, period, per_connection, counts),
            daemon=True,
        )
        for i in range(clients)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=max(0.0, deadline - time.monotonic()) + HANG_AFTER_S)
    with counts.lock:
        latencies = counts.latencies_ms
        # NumPy's default (linear) percentile: the project's one percentile definition.
        summary = (
            {
                "p50_ms": float(np.percentile(latencies, 50)),
                "p99_ms": float(np.percentile(latencies, 99)),
                "max_ms": float(np.max(latencies)),
            }
            if latencies
            else {"p50_ms": None, "p99_ms": None, "max_ms": None}
        )
        result = {
            "answered": len(latencies),
            "failed": counts.failed,
            "hung": counts.in_flight,
            "hung_connecting": counts.connecting,
            "duplicates": counts.duplicates,
            "out_of_order": counts.out_of_order,
            "connects": counts.connects,
            "connect_failures": counts.connect_failures,
            "latency": summary,
            "errors": counts.errors,
        }
    print(json.dumps(result))
    sys.stdout.flush()
    # Hung threads would keep the interpreter alive.
    import os

    os._exit(0)


if __name__ == "__main__":
    main()
