#!/usr/bin/env python3
"""Time LeRobot's full SmolVLA `predict_action_chunk` (vision tower + VLM prefix + expert) on
`lerobot/smolvla_base` shapes, and the Kairos full pipeline on the same checkpoint, side by side.

    python3 engine/tools/bench_smolvla_full.py [--batch 1,4] [--threads 2] [--iters 3] [--rounds 1]
        [--write-checkpoint DIR | --checkpoint DIR] [--kairos 'CMD' | --kairos-bin target/release/kairos]
        [--kairos-args '--precision bf16'] [--serve-rss]

The whole table in one command (what docs/BENCHMARKS.md records):

    cargo build --release -p kairos-server --bin kairos
    python3 engine/tools/bench_smolvla_full.py --write-checkpoint $CKPT --no-bench   # once, 1.1 GB
    python3 engine/tools/bench_smolvla_full.py --batch 1,4 --iters 3 --checkpoint $CKPT \
        --kairos-bin target/release/kairos --serve-rss

Time the release build, as a deployment runs it: the dev build compiles the engine at opt-level 3
too, but with debug assertions and overflow checks, which slow the vision tower down
(docs/BENCHMARKS.md has the comparison).

Shapes: SmolVLM2-500M (SigLIP 12 layers of 768 on 512x512 images, patch 16, pixel shuffle 4 ->
64 tokens per camera; 16 of the 32 SmolLM2 text layers, hidden 960, 15/5 heads of 64), expert
hidden 720, two 512x512 cameras, a 48-token instruction (`tokenizer_max_length`, padded to it),
state 6, action 6, chunk 50, 10 Euler steps. Random weights (unit-gain, seeded), f32 compute as
LeRobot runs it on a CPU.

PyTorch side: LeRobot 0.6.1's own `SmolVLAPolicy.predict_action_chunk` on an already
preprocessed batch (float images in [0,1], tokens, normalised state), under
`torch.set_num_threads(threads)`; the median of `iters` runs after one warm-up, plus the process
CPU time per run (a shared machine's waiting for a core inflates the wall time, not that).
The RSS of the model is the process's VmRSS after building it minus before, and the peak
(VmHWM) over the timed runs.

Kairos side: `--kairos 'CMD'` is a shell command template run once per batch size, alternating
with PyTorch, with `{model}`, `{batch}`, `{threads}` and `{iters}` substituted; its last stdout
line must be JSON with `median_ms` (and optionally `cpu_ms_per_run`, `rss_mb`), as
`examples/expert_timing.rs` prints (the template is a Python format string: write literal braces
as `{{` `}}`), or the JSON `kairos predict --repeat` prints (`runs_ms`, `cpu_ms_per_run`,
`peak_rss_mb`). The checkpoint it gets is `--checkpoint DIR` (an existing one), else the one
`--write-checkpoint` wrote (default: a temporary directory).

`--kairos-bin BIN` is the usual template: `BIN predict --model {model} --batch {batch} --threads
{threads} --repeat {iters} KAIROS_ARGS`, i.e. the whole Kairos pipeline (preprocessing, vision
tower, prefix, expert, postprocessing) on `batch` copies of the synthetic observation (two
mid-grey 512x512 cameras, a zero state, "pick up the cube") in one batch, after one warm-up in
the same process; `--kairos-args '...'` appends flags (e.g. `--precision bf16`). PyTorch and
Kairos alternate batch size by batch size, `--rounds` times.

`--serve-rss` (needs `--kairos-bin`): after the timings, starts `BIN serve --model CKPT` (a
config with `profile_max_batch = 1`, so the start-up profile is one batch size), runs one
`BIN robot` round with two 512x512 cameras, and reads the server's VmRSS and VmHWM from
/proc/PID/status: the memory of a served smolvla_base-shaped model.

`--write-checkpoint DIR` writes the random model as a smolvla_base-shaped checkpoint directory:
`SmolVLAPolicy.save_pretrained` (`config.json`, `model.safetensors` with the VLM's tensors in
bf16 and the expert's in f32, as lerobot/smolvla_base stores them), both processors with random
MEAN_STD stats (`policy_preprocessor.json`, `policy_postprocessor.json` and their stats files),
`vlm_config.json`, and the fixture's small `tokenizer.json` (its ids fit SmolVLM2's vocabulary).
It is about 1.2 GB: do not commit it. The PyTorch run then uses the weights as stored (the VLM
rounded to bf16), so both sides compute on the same values.
"""

import argparse
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from lerobot_env import REPO, ensure_venv  # noqa: E402

ensure_venv()

from bench_common import machine_line, status_kb, time_kairos  # noqa: E402  (sets OMP_WAIT_POLICY)

import torch  # noqa: E402

from smolvla_common import (  # noqa: E402
    BF16_PREFIX,
    SMOLVLM2_500M_SCALE_FACTOR,
    SMOLVLM2_500M_TEXT,
    SMOLVLM2_500M_VISION,
    patch_hub,
    rescale_weights,
    store_vlm_in_bf16,
)

SEED = 20261125
STATE_DIM = 6
ACTION_DIM = 6
CAMERAS = ("observation.images.camera1", "observation.images.camera2")
TOKENIZER = REPO / "engine/tests/fixtures/smolvla_tiny/tokenizer.json"


def build():
    from transformers import SmolVLMConfig

    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    vlm_config = SmolVLMConfig(
        text_config=dict(SMOLVLM2_500M_TEXT),
        vision_config=dict(SMOLVLM2_500M_VISION),
        scale_factor=SMOLVLM2_500M_SCALE_FACTOR,
    )
    patch_hub(vlm_config)
    size = SMOLVLM2_500M_VISION["image_size"]
    cfg = SmolVLAConfig(  # LeRobot's defaults are smolvla_base's: chunk 50, 16 VLM layers, 512x512, 48 tokens
        load_vlm_weights=False,
        device="cpu",
        input_features={
            "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(STATE_DIM,)),
            **{c: PolicyFeature(type=FeatureType.VISUAL, shape=(3, size, size)) for c in CAMERAS},
        },
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(ACTION_DIM,))},
    )
    torch.manual_seed(SEED)
    policy = SmolVLAPolicy(cfg).eval()
    rescale_weights(policy, SEED)
    with torch.no_grad():  # the weights as the checkpoint stores them: the VLM in bf16
        for name, p in policy.named_parameters():
            if name.startswith(BF16_PREFIX):
                p.copy_(p.to(torch.bfloat16).float())
    return policy, cfg, vlm_config


def write_checkpoint(policy, cfg, vlm_config, out: Path):
    from lerobot.policies.smolvla.processor_smolvla import make_smolvla_pre_post_processors
    from transformers import PreTrainedTokenizerFast

    out.mkdir(parents=True, exist_ok=True)
    policy.save_pretrained(out)
    store_vlm_in_bf16(out / "model.safetensors")
    gen = torch.Generator().manual_seed(SEED + 3)
    stats = {
        key: {"mean": torch.randn(d, generator=gen), "std": 0.5 + torch.rand(d, generator=gen)}
        for key, d in (("observation.state", STATE_DIM), ("action", ACTION_DIM))
    }
    tok = PreTrainedTokenizerFast(tokenizer_file=str(TOKENIZER), pad_token="<|im_end|>")
    patch_hub(vlm_config, tok)
    pre, post = make_smolvla_pre_post_processors(cfg, dataset_stats=stats)
    pre.save_pretrained(out)
    post.save_pretrained(out)
    (out / "vlm_config.json").write_text(vlm_config.to_json_string())
    shutil.copy(TOKENIZER, out / "tokenizer.json")


def make_batch(cfg, batch, gen):
    size = cfg.resize_imgs_with_padding[0]
    n = cfg.tokenizer_max_length
    out = {c: torch.rand(batch, 3, size, size, generator=gen) for c in CAMERAS}
    out["observation.state"] = torch.randn(batch, STATE_DIM, generator=gen)
    out["observation.language.tokens"] = torch.randint(3, 300, (batch, n), generator=gen)
    out["observation.language.attention_mask"] = torch.ones(batch, n, dtype=torch.bool)
    return out


@torch.no_grad()
def time_torch(policy, cfg, batch, iters):
    gen = torch.Generator().manual_seed(SEED + batch)
    obs = make_batch(cfg, batch, gen)
    noise = torch.randn(batch, cfg.chunk_size, cfg.max_action_dim, generator=gen)

    def run():
        policy.reset()
        return policy.predict_action_chunk(dict(obs), noise=noise)

    run()
    runs = []
    cpu0 = time.process_time()
    for _ in range(iters):
        t0 = time.perf_counter()
        out = run()
        runs.append((time.perf_counter() - t0) * 1e3)
        assert out.shape == (batch, cfg.chunk_size, ACTION_DIM)
    return statistics.median(runs), runs, (time.process_time() - cpu0) * 1e3 / iters


def status_of(pid):
    fields = {}
    for line in open(f"/proc/{pid}/status"):
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            fields[key] = int(value.split()[0]) / 1024
    return fields


def serve_rss(kairos_bin, model, threads):
    """RSS of `kairos serve --model model` after it has served one robot round."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    work = Path(tempfile.mkdtemp(prefix="kairos_serve_rss_"))
    config = work / "kairos.toml"
    config.write_text(
        f'listen = "127.0.0.1:{port}"\ndata_dir = "{work / "data"}"\n\n'
        f'[[engine]]\nmodel = "{model}"\nthreads = {threads}\nprofile_max_batch = 1\n'
    )
    log = open(work / "serve.log", "w")
    serve = subprocess.Popen([str(kairos_bin), "serve", "--config", str(config)], cwd=REPO,
                             stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.time() + 1800
        while "listening on" not in (work / "serve.log").read_text():
            if serve.poll() is not None or time.time() > deadline:
                raise RuntimeError(f"kairos serve did not start: {(work / 'serve.log').read_text()[-2000:]}")
            time.sleep(1)
        started = status_of(serve.pid)
        robot = subprocess.run(
            [str(kairos_bin), "robot", "--server", f"127.0.0.1:{port}", "--data-dir", str(work / "data"),
             "--rounds", "1", "--cameras", "2", "--image", "512x512"],
            cwd=REPO, capture_output=True, text=True, timeout=1800)
        if robot.returncode != 0:
            raise RuntimeError(f"kairos robot failed: {robot.stdout[-2000:]} {robot.stderr[-2000:]}")
        served = status_of(serve.pid)
        return started, served
    finally:
        serve.terminate()
        try:
            serve.wait(timeout=60)
        except subprocess.TimeoutExpired:
            serve.kill()
            serve.wait()
        log.close()
        shutil.rmtree(work, ignore_errors=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", default="1,4")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--iters", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--write-checkpoint", type=Path, help="write the random model here (about 1.2 GB)")
    ap.add_argument("--checkpoint", type=Path, help="an already written checkpoint for the Kairos side")
    ap.add_argument("--kairos", help="Kairos command template, e.g. 'target/release/kairos profile --model {model} ...'")
    ap.add_argument("--kairos-bin", type=Path, help="the kairos binary: the Kairos side is `kairos predict --repeat`")
    ap.add_argument("--kairos-args", default="", help="more flags for `kairos predict`, e.g. '--precision bf16'")
    ap.add_argument("--serve-rss", action="store_true", help="also the RSS of `kairos serve` after one robot round")
    ap.add_argument("--no-bench", action="store_true", help="only write the checkpoint")
    args = ap.parse_args()
    batches = [int(b) for b in args.batch.split(",")]
    torch.set_num_threads(args.threads)
    if args.kairos_bin and not args.kairos:
        bin_ = shlex.quote(str(args.kairos_bin.resolve()))
        args.kairos = (f"{bin_} predict --model {{model}} --batch {{batch}} --threads {{threads}} "
                       f"--repeat {{iters}} {args.kairos_args}")
    elif args.kairos_args:
        ap.error("--kairos-args needs --kairos-bin")
    if args.serve_rss and not args.kairos_bin:
        ap.error("--serve-rss needs --kairos-bin")

    rss0 = status_kb("VmRSS")
    policy, cfg, vlm_config = build()
    rss_model = (status_kb("VmRSS") - rss0) / 1024
    params = sum(p.numel() for p in policy.parameters())
    ckpt = args.write_checkpoint
    tmp = None
    if args.checkpoint is not None:
        if ckpt is not None:
            ap.error("--checkpoint and --write-checkpoint exclude each other")
    elif ckpt is None and args.kairos:
        tmp = tempfile.mkdtemp(prefix="smolvla_base_random_")
        ckpt = Path(tmp)
    if ckpt is not None:
        write_checkpoint(policy, cfg, vlm_config, ckpt)
        size = sum(f.stat().st_size for f in ckpt.iterdir()) / 1e9
        print(f"# wrote {ckpt} ({size:.2f} GB): {sorted(p.name for p in ckpt.iterdir())}", flush=True)
    if args.no_bench:
        return
    if args.checkpoint is not None:
        ckpt = args.checkpoint.resolve()

    print(machine_line(f"torch {torch.__version__} ({torch.get_num_threads()} threads), "))
    print(f"# model: {params / 1e6:.0f} M parameters (f32 in memory), RSS after build +{rss_model:.0f} MB")
    results = {}
    try:
        for _ in range(args.rounds):
            for b in batches:
                load = open("/proc/loadavg").read().split()[0]
                pt, pt_runs, pt_cpu = time_torch(policy, cfg, b, args.iters)
                line = (f"#   B={b} (load avg {load}): pytorch runs {[round(r) for r in pt_runs]} ms, "
                        f"cpu {pt_cpu:.0f} ms/run")
                ka = None
                if args.kairos:
                    ka = time_kairos(args.kairos, ckpt, b, args.threads, args.iters, REPO)
                    line += f"; kairos {ka}"
                print(line, flush=True)
                kept = results.get(b)
                ratio = ka["median_ms"] / pt if ka else 0.0
                if kept is None or (ratio > kept[2] if ka else pt < kept[0]):  # conservative for Kairos
                    results[b] = (pt, pt_cpu, ratio, ka)
        served = None
        if args.serve_rss:
            print(f"# serving {ckpt} to one `kairos robot` round ...", flush=True)
            try:
                served = serve_rss(args.kairos_bin.resolve(), ckpt, args.threads)
            except (RuntimeError, OSError, subprocess.SubprocessError) as e:
                print(f"# serve RSS not measured: {e}", flush=True)
    finally:
        if tmp:
            shutil.rmtree(tmp, ignore_errors=True)
    print(f"# PyTorch process peak RSS (VmHWM) {status_kb('VmHWM') / 1024:.0f} MB")
    print("| batch | PyTorch (LeRobot) ms | PyTorch CPU ms/run | Kairos ms | Kairos CPU ms/run "
          "| Kairos / PyTorch (wall) | Kairos / PyTorch (CPU) | Kairos peak RSS MB |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for b in batches:
        pt, pt_cpu, ratio, ka = results[b]
        kcell = f"{ka['median_ms']:.0f}" if ka else "n/a"
        kcpu = ka.get("cpu_ms_per_run") if ka else None
        rcell = f"{ratio:.2f}" if ka else "n/a"
        rcpu = f"{kcpu / pt_cpu:.2f}" if kcpu else "n/a"
        rss = ka.get("rss_mb", "n/a") if ka else "n/a"
        print(f"| {b} | {pt:.0f} | {pt_cpu:.0f} | {kcell} | {kcpu if kcpu else 'n/a'} | {rcell} | {rcpu} | {rss} |")
    if served is not None:
        started, after = served
        print(f"# kairos serve --model {ckpt}: VmRSS {started['VmRSS']:.0f} MB after start-up "
              f"(model loaded, batch 1 profiled), VmRSS {after['VmRSS']:.0f} MB and peak VmHWM "
              f"{after['VmHWM']:.0f} MB after one robot round (2 cameras 512x512)")


if __name__ == "__main__":
    main()
