#!/usr/bin/env python3
"""Round latency: the Python package (kairos.Client) vs the Rust SDK, same server, same model.

Starts one `kairos serve` (target/debug/kairos, or KAIROS_BIN) in a temporary data directory,
then alternates blocks of sequential rounds through the Rust SDK (the `round_latency` example of
kairos-sdk, built with `cargo build -p kairos-sdk --example round_latency`) and through
kairos.Client, each in a task of its own with the same observation, and prints p50/p99/max per
client. Percentiles are NumPy's default (linear interpolation), the same definition as the
server's `stats` module.

    python sdk/python/benches/round_latency.py --rounds 200 --blocks 2 --image 64
"""

import argparse
import pathlib
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=200, help="rounds per client per block")
    parser.add_argument("--blocks", type=int, default=2, help="alternating blocks (Rust, Python, Rust, ...)")
    parser.add_argument("--image", type=int, default=64, help="side of the square RGB camera image")
    parser.add_argument("--example", default=str(ROOT / "target" / "debug" / "examples" / "round_latency"),
                        help="the Rust example binary")
    args = parser.parse_args()
    results = {"Rust SDK (BlockingClient)": [], "Python package (kairos.Client.infer)": []}
    with tempfile.TemporaryDirectory() as tmp:
        server = Server(pathlib.Path(tmp) / "kairos-data")
        server.start()
        try:
            for _ in range(args.blocks):
                results["Rust SDK (BlockingClient)"] += rust_rounds(server, args.rounds, args.image,
                                                                    pathlib.Path(args.example))
                results["Python package (kairos.Client.infer)"] += python_rounds(server, args.rounds, args.image)
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
