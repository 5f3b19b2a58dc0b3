#!/usr/bin/env python3
"""Time LeRobot's PyTorch SmolVLA denoise loop and Kairos's expert on the same shapes, side by side.

    python3 engine/tools/bench_vs_pytorch.py [--batch 1,4,16] [--threads 2] [--iters 5] [--rounds 2]

Shapes are `lerobot/smolvla_base`'s: SmolVLM2-500M text config (hidden 960, 15/5 heads of 64),
16 layers, expert hidden 720, prefix 177 tokens (2 cameras x 64 + 48 language + 1 state),
chunk 50, 10 Euler steps; both sides use random weights and a random prefix KV cache.

PyTorch side: LeRobot 0.6.1's own `VLAFlowMatching`, and exactly the loop `sample_actions` runs
after the VLM prefill: `euler_integrate(denoise_step, noise, num_steps)` over a filled
`DynamicCache`, under `torch.no_grad()`, `torch.set_num_threads(threads)`.

Kairos side: `cargo run --release -p kairos-engine --example expert_timing` with the same batch
sizes and thread count. Batch sizes alternate between the two so that both see the same machine
load; every cell is the median of `iters` runs after one warm-up. With `--rounds > 1` the table
keeps, per batch size, the round in which PyTorch did relatively best (the conservative choice).
On a shared machine wall time includes waiting for a core; the last column compares process CPU
time per run, which that waiting does not inflate.
"""

import argparse
import json
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from lerobot_env import REPO, ensure_venv  # noqa: E402

ensure_venv()

import torch  # noqa: E402

from smolvla_common import SMOLVLM2_500M_TEXT, patch_hub  # noqa: E402

PREFIX = 177
TEXT_CONFIG = SMOLVLM2_500M_TEXT
# The vision tower is not used by the denoise loop; a tiny one keeps construction fast.
VISION_CONFIG = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=2,
                     image_size=32, patch_size=8)


def build_model():
    from transformers import SmolVLMConfig

    from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig
    from lerobot.policies.smolvla.modeling_smolvla import VLAFlowMatching

    vlm_config = SmolVLMConfig(text_config=dict(TEXT_CONFIG), vision_config=dict(VISION_CONFIG), scale_factor=2)

    patch_hub(vlm_config)
    cfg = SmolVLAConfig(load_vlm_weights=False, device="cpu")  # all LeRobot defaults otherwise
    model = VLAFlowMatching(cfg).eval()
    return model, cfg


@torch.no_grad()
def time_torch(model, cfg, batch, iters):
    from transformers import DynamicCache

    from lerobot.policies.common.flow_matching import euler_integrate

    text = model.vlm_with_expert.config.text_config
    cache = DynamicCache()
    for layer in range(cfg.num_vlm_layers):
        shape = (batch, text.num_key_value_heads, PREFIX, text.head_dim)
        cache.update(torch.randn(shape), torch.randn(shape), layer)
    pad = torch.ones(batch, PREFIX, dtype=torch.bool)
    noise = torch.randn(batch, cfg.chunk_size, cfg.max_action_dim)

    def run():
        return euler_integrate(
            lambda x, t: model.denoise_step(x_t=x, prefix_pad_masks=pad, past_key_values=cache, timestep=t),
            noise,
            cfg.num_steps,
        )

    run()
    runs = []
    cpu0 = time.process_time()
    for _ in range(iters):
        t0 = time.perf_counter()
        out = run()
        runs.append((time.perf_counter() - t0) * 1e3)
        assert out.shape == (batch, cfg.chunk_size, cfg.max_action_dim)
    cpu_ms = (time.process_time() - cpu0) * 1e3 / iters
    return statistics.median(runs), runs, cpu_ms


def time_kairos(batch, threads, iters, kernels):
    cmd = ["cargo", "run", "--quiet", "--release", "-p", "kairos-engine", "--example", "expert_timing", "--",
           "--batch", str(batch), "--threads", str(threads), "--iters", str(iters), "--kernels", kernels]
    out = subprocess.run(cmd, cwd=REPO, check=True, capture_output=True, text=True)
    row = json.loads(out.stdout.strip().splitlines()[-1])
    return row["median_ms"], row["runs"], row["cpu_ms_per_run"], out.stderr.strip()


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", default="1,4,16")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--iters", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--kernels", default="fast", choices=["fast", "portable", "candle"])
    args = ap.parse_args()
    batches = [int(b) for b in args.batch.split(",")]

    torch.set_num_threads(args.threads)
    subprocess.run(["cargo", "build", "--quiet", "--release", "-p", "kairos-engine", "--example", "expert_timing"],
                   cwd=REPO, check=True)
    model, cfg = build_model()
    cpu = next((ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name")), "?")
    print(f"# {cpu}, {args.threads} threads, torch {torch.__version__} ({torch.get_num_threads()} threads), "
          f"python {platform.python_version()}; prefix {PREFIX}, chunk {cfg.chunk_size}, {cfg.num_steps} steps")
    results = {}
    for _ in range(args.rounds):
        for b in batches:
            load = open("/proc/loadavg").read().split()[0]
            pt, pt_runs, pt_cpu = time_torch(model, cfg, b, args.iters)
            ka, ka_runs, ka_cpu, desc = time_kairos(b, args.threads, args.iters, args.kernels)
            print(f"#   B={b} (load avg {load}): pytorch runs {[round(r) for r in pt_runs]} cpu {pt_cpu:.0f} ms/run; "
                  f"kairos ({desc}) runs {[round(r) for r in ka_runs]} cpu {ka_cpu:.0f} ms/run", flush=True)
            kept = results.get(b)
            # Conservative: keep the round with the highest Kairos / PyTorch ratio.
            if kept is None or ka / pt > kept[1] / kept[0]:
                results[b] = (pt, ka, pt_cpu, ka_cpu)
    print("| batch | PyTorch (LeRobot) ms | Kairos ms | Kairos / PyTorch | CPU-time ratio |")
    print("|---:|---:|---:|---:|---:|")
    for b in batches:
        pt, ka, pt_cpu, ka_cpu = results[b]
        print(f"| {b} | {pt:.0f} | {ka:.0f} | {ka / pt:.2f} | {ka_cpu / pt_cpu:.2f} |")


if __name__ == "__main__":
    main()
