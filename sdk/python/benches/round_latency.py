#!/usr/bin/env python3
"""Round latency: the Python package (kairos.Client) vs the Rust SDK vs openpi-client, same server, same model.

Starts one `kairos serve` (target/debug/kairos, or KAIROS_BIN) in a temporary data directory,
then alternates blocks of sequential rounds through the Rust SDK (the `round_latency` example of
kairos-sdk, built with `cargo build -p kairos-sdk --example round_latency`) and through
kairos.Client, each in a task of its own with the same observation, and prints p50/p99/max per
client. Percentiles are NumPy's default (linear interpolation), the same definition as the
server's `stats` module.

    python sdk/python/benches/round_latency.py --rounds 200 --blocks 2 --image 64

With `--openpi-python PY` (a Python with `openpi-client` 0.1.2 installed, e.g. `.venv-openpi/bin/python`:
it needs numpy<2, so it lives in a venv of its own), the server also serves openpi's websocket
protocol and every block adds `--rounds` calls of the unmodified `WebsocketClientPolicy.infer`
(`tests/python/openpi_check.py latency`; two 32×32 cameras, since its observation is LIBERO-shaped).
"""

import argparse
import json
import pathlib
import socket
import subprocess
import sys
import tempfile
import time

import numpy as np

import kairos

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))
from live_server import ROOT, Server  # noqa: E402

WARM_UP = 10  # as the Rust example


def python_rounds(server: Server, rounds: int, side: int) -> list:
    with kairos.Client.from_data_dir(server.data_dir, server.address) as client:
        state_dim = client.model["state_dim"]
        client.start_task()
        latencies = []
        for step in range(WARM_UP + rounds):
            observation = {
                "state": np.linspace(0.0, 1.0, state_dim, dtype=np.float32) + np.float32(0.01 * step),
                "images": {"front": np.full((side, side, 3), step % 256, dtype=np.uint8)},
                "instruction": "pick up the cube",
            }
            started = time.perf_counter()
            client.infer(observation)
            if step >= WARM_UP:
                latencies.append(((time.perf_counter() - started) * 1e6, client.last_round["total_us"]))
        client.end_task()
    return latencies


def rust_rounds(server: Server, rounds: int, side: int, binary: pathlib.Path) -> list:
    run = subprocess.run([str(binary), server.address, str(server.data_dir), str(rounds), str(side)],
                         capture_output=True, text=True, check=True)
    return [tuple(map(float, line.split())) for line in run.stdout.splitlines()]


def openpi_rounds(server: Server, rounds: int, python: str, port: int) -> list:
    script = ROOT / "tests" / "python" / "openpi_check.py"
    run = subprocess.run([python, str(script), "latency", "127.0.0.1", str(port), server.token, str(rounds)],
                         capture_output=True, text=True, check=True)
    # (round µs, the server's part µs), as the other two clients report.
    return [(r * 1e3, s * 1e3) for r, s in json.loads(run.stdout.splitlines()[-1])["samples"]]


def free_tcp_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=200, help="rounds per client per block")
    parser.add_argument("--blocks", type=int, default=2, help="alternating blocks (Rust, Python, Rust, ...)")
    parser.add_argument("--image", type=int, default=64, help="side of the square RGB camera image")
    parser.add_argument("--example", default=str(ROOT / "target" / "debug" / "examples" / "round_latency"),
                        help="the Rust example binary")
    parser.add_argument("--openpi-python", help="a Python with openpi-client installed: adds openpi-client blocks")
    args = parser.parse_args()
    results = {"Rust SDK (BlockingClient)": [], "Python package (kairos.Client.infer)": []}
    openpi_port = free_tcp_port() if args.openpi_python else None
    if args.openpi_python:
        results["openpi-client 0.1.2 (WebsocketClientPolicy.infer)"] = []
    with tempfile.TemporaryDirectory() as tmp:
        extra = ["--openpi-listen", f"127.0.0.1:{openpi_port}"] if openpi_port else []
        server = Server(pathlib.Path(tmp) / "kairos-data", extra)
        server.start()
        try:
            for _ in range(args.blocks):
                results["Rust SDK (BlockingClient)"] += rust_rounds(server, args.rounds, args.image,
                                                                    pathlib.Path(args.example))
                results["Python package (kairos.Client.infer)"] += python_rounds(server, args.rounds, args.image)
                if openpi_port:
                    results["openpi-client 0.1.2 (WebsocketClientPolicy.infer)"] += openpi_rounds(
                        server, args.rounds, args.openpi_python, openpi_port)
        finally:
            server.stop()
    print(f"{args.blocks} blocks x {args.rounds} sequential rounds per client, {args.image}x{args.image} RGB image")
    print("Round latency (call to chunk), and of it outside the server (latency - the server's total_us:")
    print("client library, QUIC, loopback)")
    print("| client | rounds | p50 ms | p99 ms | max ms | outside server p50 ms | p99 ms |")
    print("|---|---|---|---|---|---|---|")
    for name, values in results.items():
        values = np.array(values) / 1e3
        latency, outside = values[:, 0], values[:, 0] - values[:, 1]
        print(f"| {name} | {latency.size} | {np.percentile(latency, 50):.2f} | "
              f"{np.percentile(latency, 99):.2f} | {latency.max():.2f} | "
              f"{np.percentile(outside, 50):.2f} | {np.percentile(outside, 99):.2f} |")


if __name__ == "__main__":
    main()
