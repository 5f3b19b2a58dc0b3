"""Drives `kairos serve --openpi-listen` with the unmodified openpi-client from PyPI.

Run by tests/tests/it/openpi.rs with the Python of a venv where `openpi-client==0.1.2` is
installed (scripts/test.sh makes it). Each mode prints one JSON object on stdout; the Rust test
asserts on it. Usage:

    openpi_check.py basic      HOST PORT KEY ROUNDS
    openpi_check.py concurrent HOST PORT KEY CLIENTS ROUNDS
    openpi_check.py auth       HOST PORT
    openpi_check.py garbage    HOST PORT KEY
    openpi_check.py latency    HOST PORT KEY CALLS
"""

import json
import sys
import threading
import time

import numpy as np
import websockets.exceptions
import websockets.sync.client
from openpi_client import msgpack_numpy
from openpi_client import websocket_client_policy


def observation(metadata, seed):
    """A LIBERO-shaped observation for the served model's shapes."""
    rng = np.random.default_rng(seed)
    return {
        "observation/image": rng.integers(0, 256, (32, 32, 3), dtype=np.uint8),
        "observation/wrist_image": rng.integers(0, 256, (32, 32, 3), dtype=np.uint8),
        # float64, as numpy makes it: the server converts.
        "observation/state": rng.uniform(-0.2, 0.2, metadata["state_dim"]),
        "prompt": "put the bowl on the plate",
    }


def describe(reply):
    actions = reply["actions"]
    return {
        "shape": list(actions.shape),
        "dtype": str(actions.dtype),
        "finite": bool(np.isfinite(actions).all()),
        "server_timing": reply["server_timing"],
        "policy_timing": reply["policy_timing"],
        "kairos": reply["kairos"],
    }


def basic(host, port, key, rounds):
    policy = websocket_client_policy.WebsocketClientPolicy(host, port, api_key=key)
    metadata = policy.get_server_metadata()
    replies = [describe(policy.infer(observation(metadata, i))) for i in range(rounds)]
    policy._ws.close()
    return {"metadata": metadata, "replies": replies}


def concurrent(host, port, key, clients, rounds):
    policies = [
        websocket_client_policy.WebsocketClientPolicy(host, port, api_key=key)
        for _ in range(clients)
    ]
    start = threading.Barrier(clients)
    results = [None] * clients
    errors = []

    def robot(i):
        try:
            metadata = policies[i].get_server_metadata()
            start.wait()
            replies = []
            for r in range(rounds):
                replies.append(describe(policies[i].infer(observation(metadata, 100 * i + r))))
            results[i] = {"task": metadata["task"], "replies": replies}
            policies[i]._ws.close()
        except Exception as e:  # reported to the Rust test, which fails on it
            errors.append(repr(e))

    threads = [threading.Thread(target=robot, args=(i,)) for i in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return {"clients": results, "errors": errors}


def refused_status(host, port, key):
    """Connects as openpi-client does; returns the HTTP status of the refusal, or None."""
    try:
        policy = websocket_client_policy.WebsocketClientPolicy(host, port, api_key=key)
    except websockets.exceptions.InvalidStatus as e:
        return e.response.status_code
    policy._ws.close()
    return None


def auth(host, port):
    return {
        "wrong_key": refused_status(host, port, "not-a-robot-token"),
        "no_key": refused_status(host, port, None),
    }


def raw_exchange(host, port, key, payload):
    """Sends one raw message after the metadata; returns (text reply, close code)."""
    with websockets.sync.client.connect(
        f"ws://{host}:{port}",
        compression=None,
        max_size=None,
        additional_headers={"Authorization": f"Api-Key {key}"},
    ) as ws:
        ws.recv()  # metadata
        ws.send(payload)
        reply = ws.recv()
        try:
            extra = ws.recv()
            return {"reply": reply, "after": repr(extra), "close_code": None}
        except websockets.exceptions.ConnectionClosed as e:
            code = e.rcvd.code if e.rcvd is not None else None
            return {"reply": reply if isinstance(reply, str) else repr(reply), "close_code": code}


def garbage(host, port, key):
    good = websocket_client_policy.WebsocketClientPolicy(host, port, api_key=key)
    metadata = good.get_server_metadata()
    before = describe(good.infer(observation(metadata, 1)))
    wrong_state = observation(metadata, 2)
    wrong_state["observation/state"] = np.zeros(metadata["state_dim"] + 3, dtype=np.float32)
    wrong_image = observation(metadata, 3)
    wrong_image["observation/image"] = np.zeros((4, 4), dtype=np.uint8)
    bad_dtype = observation(metadata, 4)
    bad_dtype["observation/state"] = np.array(["a", "b"])
    cases = {
        "not_msgpack": b"\xc1\x00garbage",
        "truncated": b"\x85\xa1a",
        "not_a_map": msgpack_numpy.packb([1, 2, 3]),
        "wrong_state_len": msgpack_numpy.packb(wrong_state),
        "wrong_image_shape": msgpack_numpy.packb(wrong_image),
        "string_state": msgpack_numpy.packb(bad_dtype),
        "text_frame": "hello",
        # Over the test server's 256 KiB frame limit.
        "too_large": b"\x80" + bytes(300 * 1024),
    }
    results = {name: raw_exchange(host, port, key, payload) for name, payload in cases.items()}
    # openpi-client itself sees the error text as a RuntimeError.
    client_error = None
    bad = websocket_client_policy.WebsocketClientPolicy(host, port, api_key=key)
    try:
        bad.infer(wrong_state)
    except RuntimeError as e:
        client_error = str(e)
    after = describe(good.infer(observation(metadata, 5)))
    good._ws.close()
    return {
        "cases": results,
        "client_error": client_error,
        "before": before,
        "after": after,
    }


def latency(host, port, key, calls):
    """Round latency of `calls` infer() calls, and its parts: the server's time (arrival to
    answer, `server_timing.infer_ms`), what the server added to the forward pass
    (`infer_ms - inference_ms`), and the rest (network, websocket, msgpack, numpy: client side)."""
    policy = websocket_client_policy.WebsocketClientPolicy(host, port, api_key=key)
    metadata = policy.get_server_metadata()
    obs = observation(metadata, 0)
    policy.infer(obs)  # warm-up
    rounds, added, client = [], [], []
    for _ in range(calls):
        started = time.perf_counter()
        reply = policy.infer(obs)
        ms = (time.perf_counter() - started) * 1e3
        timing = reply["server_timing"]
        rounds.append(ms)
        added.append(timing["infer_ms"] - timing["inference_ms"])
        client.append(ms - timing["infer_ms"])
    policy._ws.close()

    # NumPy's default (linear) percentile: the project's one percentile definition.
    def summary(samples):
        return {
            "p50_ms": float(np.percentile(samples, 50)),
            "p95_ms": float(np.percentile(samples, 95)),
            "p99_ms": float(np.percentile(samples, 99)),
            "mean_ms": float(np.mean(samples)),
        }

    return {
        "calls": calls,
        # Per call: round ms and the server's part (arrival to answer), for callers that pool
        # samples across runs (sdk/python/benches/round_latency.py).
        "samples": [[r, r - c] for r, c in zip(rounds, client)],
        "round": summary(rounds),
        "server_added": summary(added),
        "network_client": summary(client),
    }


def main(argv):
    mode, host, port = argv[1], argv[2], int(argv[3])
    if mode == "basic":
        out = basic(host, port, argv[4], int(argv[5]))
    elif mode == "concurrent":
        out = concurrent(host, port, argv[4], int(argv[5]), int(argv[6]))
    elif mode == "auth":
        out = auth(host, port)
    elif mode == "garbage":
        out = garbage(host, port, argv[4])
    elif mode == "latency":
        out = latency(host, port, argv[4], int(argv[5]))
    else:
        raise SystemExit(f"unknown mode {mode}")
    print(json.dumps(out))


if __name__ == "__main__":
    main(sys.argv)
