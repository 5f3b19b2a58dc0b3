#!/usr/bin/env python3
"""Time LeRobot's full π0.5 (or π0) `predict_action_chunk` on base shapes, and the Kairos full
pipeline (`kairos predict --repeat`) on the same checkpoint, side by side, with memory.

    python3 engine/tools/bench_pi_full.py [--family pi05|pi0] [--small] [--batch 1,4] [--threads 2]
        [--iters 3] [--rounds 1] [--dtype bfloat16|float32] [--precisions f32,bf16]
        [--write-checkpoint DIR [--no-bench] | --checkpoint DIR] [--kairos-bin BIN] [--kairos-args '...']

The full run (`docs/BENCHMARKS.md`), the checkpoint written once (π0.5, `--dtype bfloat16`:
4.14 G parameters, 9.4 GB on disk; `float32`: 16.6 GB):

    cargo build --release -p kairos-cli --bin kairos
    python3 engine/tools/bench_pi_full.py --write-checkpoint $CKPT --no-bench
    python3 engine/tools/bench_pi_full.py --checkpoint $CKPT --kairos-bin target/release/kairos

What it measures, and how: each measurement is a fresh process that loads the checkpoint and
runs one untimed warm-up and `--iters` timed predictions of B identical synthetic observations
(three mid-grey 224x224 cameras, a zero state, "pick up the cube"), recording the median wall
time, the CPU time per run, the loaded model's RSS and the process's peak RSS (the kernel's
`ru_maxrss`, loading included). PyTorch is LeRobot 0.6.1's own `predict_action_chunk` in float32
on the batch LeRobot's preprocessor made from that observation, with fixed noise (pre- and
postprocessing untimed); Kairos is `kairos predict --repeat`, its whole pipeline timed, once per
`--precisions` entry. The two alternate batch size by batch size, `--rounds` times, never
holding the model at the same time; the table keeps PyTorch's fastest and Kairos's slowest round
and checks the targets in `TARGETS` against PyTorch's float32 time, and Kairos's peak RSS against
PyTorch's. PyTorch's model RSS is VmRSS after loading minus before; Kairos's is shown when
`kairos predict` reports `model_rss_mb`.

The checkpoint (`--write-checkpoint DIR`, a temporary directory by default): LeRobot's
`PI05Policy` / `PI0Policy.save_pretrained` (`config.json`, `model.safetensors`), both processors
with random statistics (`policy_preprocessor.json`, `policy_postprocessor.json` and their stats
files) and a tokenizer. Shapes are LeRobot's hard-coded base ones: PaliGemma (SigLIP so400m/14
at 224x224, Gemma 2B: 18 layers, width 2048, 8 heads, 1 KV head, head dim 256, vocabulary
257 152) and the Gemma 300M expert (width 1024); three 224x224 cameras, state 8, action 7,
chunk 50, 10 steps, the family's default normalisation and tokenizer length (π0.5: QUANTILES,
200 tokens; π0: MEAN_STD, 48). LeRobot's `save_pretrained` writes every parameter in the dtype
the policy holds it in: with the config's `dtype: "float32"` (PI05Config's and PI0Config's
default) all float32; with `"bfloat16"` (`--dtype`, the default here: weights stored in bf16)
everything is cast to bfloat16 except the vision tower, the projector and the RMSNorms (with
π0.5's adaptive-norm projections), which stay float32. The state dict includes PaliGemma's and
the expert's `lm_head` (untied, unused by inference).
The PyTorch side loads the stored values into float32 modules (`dtype: "float32"`), so both
sides compute on the same numbers. Weights are seeded unit-gain random values
(`smolvla_common.rescale_weights`), written without LeRobot's random initialisation first
(`transformers.initialization.no_init_weights`), so the writer holds the model once, in its
stored dtypes. The tokenizer (`pi_common.write_tokenizer`) is a Gemma-style BPE trained offline
on a small corpus, its vocabulary filled with unused tokens up to PaliGemma's 257 152 ids, so
the embedding table has its real shape; the prompt's tokens are the trained ones. `--small`
writes the same structure at toy widths and depths (`pi_common.ToySizes`) with the real image
size, prompt length, chunk and vocabulary, to check the whole tool in a minute.
"""

import argparse
import gc
import json
import math
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from lerobot_env import REPO, ensure_venv  # noqa: E402

ensure_venv()

from bench_common import (  # noqa: E402
    machine_line,
    reset_peak_rss,
    run_json,
    safetensors_header,
    status_kb,
    time_kairos,
)

SEED = 20261128
STATE_DIM = 8
ACTION_DIM = 7
IMAGE = 224
CAMERAS = (
    "observation.images.base_0_rgb",
    "observation.images.left_wrist_0_rgb",
    "observation.images.right_wrist_0_rgb",
)
TASK = "pick up the cube"
PALIGEMMA_VOCAB = 257152  # pi_common's; the parent process imports no torch
GEMMA_2B_WIDTH = 2048
EMBED_KEY = "model.paligemma_with_expert.paligemma.model.language_model.embed_tokens.weight"
TARGETS = {"f32": 0.75, "bf16": 0.4}  # Kairos time / PyTorch float32 time, issue 31


def progress(t0, what):
    print(f"# [{time.perf_counter() - t0:7.1f} s] {what}", flush=True)


def toy_sizes(small):
    """`--small`: toy widths and depths, PaliGemma's real vocabulary (so its tokenizer is checked)."""
    from pi_common import ToySizes

    return ToySizes(vocab=PALIGEMMA_VOCAB) if small else None


def write_checkpoint(family, small, dtype, out: Path):
    """The random checkpoint, as LeRobot's `save_pretrained` writes it (see the docstring)."""
    import torch
    from transformers.initialization import no_init_weights

    import pi_common
    from lerobot.configs.types import FeatureType, PolicyFeature
    from pi_common import hf_tokenizer, patch_lerobot, policy_classes, write_tokenizer
    from smolvla_common import feature_stats
    from smolvla_common import rescale_weights

    assert pi_common.PALIGEMMA_VOCAB == PALIGEMMA_VOCAB

    t0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    write_tokenizer(out / "tokenizer.json", PALIGEMMA_VOCAB)
    tokenizer = hf_tokenizer(out / "tokenizer.json")
    patch_lerobot(tokenizer, toy_sizes(small))
    progress(t0, f"tokenizer.json: {len(tokenizer)} tokens")

    Config, Policy, make_processors = policy_classes(family)
    cfg = Config(
        dtype=dtype,
        device="cpu",
        input_features={
            "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(STATE_DIM,)),
            **{c: PolicyFeature(type=FeatureType.VISUAL, shape=(3, IMAGE, IMAGE)) for c in CAMERAS},
        },
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(ACTION_DIM,))},
    )
    # Every parameter is overwritten below: LeRobot's random initialisation would only cost time
    # and hold the whole model in float32 once (16.6 GB for π0.5 at base shapes).
    with no_init_weights():
        policy = Policy(cfg).eval()
    params = sum(p.numel() for p in policy.parameters())
    progress(t0, f"{family} built: {params / 1e6:.1f} M parameters, RSS {status_kb('VmRSS') / 1e6:.1f} GB")

    shown = [0]

    def weights_progress(fraction):
        if int(fraction * 10) > shown[0]:
            shown[0] = int(fraction * 10)
            progress(t0, f"random weights {100 * fraction:3.0f} %, RSS {status_kb('VmRSS') / 1e6:.1f} GB")

    rescale_weights(policy, SEED, progress=weights_progress)
    policy.save_pretrained(out)
    del policy
    gc.collect()
    progress(t0, "model.safetensors written")

    gen = torch.Generator().manual_seed(SEED + 7)
    stats = {"observation.state": feature_stats(gen, STATE_DIM, 2.0), "action": feature_stats(gen, ACTION_DIM, 1.5)}
    pre, post = make_processors(cfg, dataset_stats=stats)
    pre.save_pretrained(out)
    post.save_pretrained(out)
    by_dtype = {}
    for info in safetensors_header(out / "model.safetensors").values():
        by_dtype[info["dtype"]] = by_dtype.get(info["dtype"], 0) + math.prod(info["shape"])
    size = sum(f.stat().st_size for f in out.iterdir()) / 1e9
    stored = ", ".join(f"{n / 1e6:.1f} M {dt}" for dt, n in sorted(by_dtype.items()))
    progress(t0, f"wrote {out} ({size:.2f} GB; parameters stored: {stored}): {sorted(p.name for p in out.iterdir())}")


def torch_config(ckpt: Path, small):
    """The checkpoint's config for a float32 PyTorch run, with LeRobot patched to build it offline."""
    from lerobot.configs.policies import PreTrainedConfig
    from pi_common import hf_tokenizer, patch_lerobot, policy_classes

    patch_lerobot(hf_tokenizer(ckpt / "tokenizer.json"), toy_sizes(small))
    cfg = PreTrainedConfig.from_pretrained(ckpt)
    cfg.dtype = "float32"
    cfg.device = "cpu"
    policy_classes(cfg.type)  # imports the policy's modules before anything is measured
    return cfg


def read_safetensors(path: Path):
    """`(name, tensor)` for each tensor of a safetensors file, read one at a time with plain reads.

    Not `safe_open`: its memory map keeps every page it has read resident (and counted in the
    process's RSS) until it is closed, which would add the file's size to the loader's peak.
    """
    import torch

    dtypes = {"F32": torch.float32, "BF16": torch.bfloat16, "F16": torch.float16, "F64": torch.float64,
              "I64": torch.int64, "I32": torch.int32, "U8": torch.uint8, "BOOL": torch.bool}
    with open(path, "rb") as f:
        n = int.from_bytes(f.read(8), "little")
        header = json.loads(f.read(n))
        header.pop("__metadata__", None)
        for name, info in sorted(header.items(), key=lambda kv: kv[1]["data_offsets"][0]):
            start, end = info["data_offsets"]
            f.seek(8 + n + start)
            data = bytearray(f.read(end - start))
            t = torch.frombuffer(data, dtype=dtypes[info["dtype"]]) if data else torch.empty(0)
            yield name, t.reshape(info["shape"])


def load_torch_policy(ckpt: Path, cfg):
    """LeRobot's policy class for the checkpoint, in float32, with the stored values.

    LeRobot's own `from_pretrained` initialises the model at random and then reads the whole
    safetensors file into memory before copying it in: the float32 model and the file at once.
    This builds the same modules without the random initialisation and copies the file in tensor
    by tensor, so the loaded model is what LeRobot runs, at the memory a deployment would see.
    """
    import torch
    from transformers.initialization import no_init_weights

    from pi_common import policy_classes

    _, Policy, _ = policy_classes(cfg.type)
    with no_init_weights():
        policy = Policy(cfg).eval()
    state = policy.state_dict()
    loaded = set()
    with torch.no_grad():
        for k, t in read_safetensors(ckpt / "model.safetensors"):
            if k not in state:
                raise KeyError(f"{ckpt}/model.safetensors: unexpected tensor {k}")
            if state[k].shape != t.shape:
                raise ValueError(f"{ckpt}/model.safetensors: {k} is {list(t.shape)}, LeRobot's "
                                 f"module holds {list(state[k].shape)}")
            state[k].copy_(t)
            loaded.add(k)
    # save_pretrained drops a tensor that shares storage with a saved one (tied weights).
    saved_ptrs = {state[k].data_ptr() for k in loaded}
    missing = [k for k in state if k not in loaded and state[k].data_ptr() not in saved_ptrs]
    buffers = {k for k, _ in policy.named_buffers()}
    missing = [k for k in missing if k not in buffers]
    if missing:
        raise KeyError(f"{ckpt}/model.safetensors lacks {missing[:5]} ({len(missing)} tensors)")
    return policy


def torch_worker(ckpt: Path, small, batch, threads, iters):
    """One PyTorch measurement in this process; prints its JSON as the last line."""
    import torch

    from lerobot.processor import PolicyProcessorPipeline

    torch.set_num_threads(threads)
    cfg = torch_config(ckpt, small)
    rss0 = status_kb("VmRSS")
    policy = load_torch_policy(ckpt, cfg)
    model_rss = (status_kb("VmRSS") - rss0) / 1024
    load_peak = status_kb("VmHWM") / 1024
    pre = PolicyProcessorPipeline.from_pretrained(ckpt, config_filename="policy_preprocessor.json")
    obs = {c: torch.full((batch, 3, IMAGE, IMAGE), 0.5) for c in cfg.image_features}
    obs["observation.state"] = torch.zeros(batch, STATE_DIM)
    obs["task"] = [TASK] * batch
    prepared = pre(obs)
    gen = torch.Generator().manual_seed(SEED + batch)
    noise = torch.randn(batch, cfg.chunk_size, cfg.max_action_dim, generator=gen)

    @torch.no_grad()
    def run():
        policy.reset()
        return policy.predict_action_chunk(dict(prepared), noise=noise)

    reset_peak_rss()
    out = run()
    assert out.shape == (batch, cfg.chunk_size, ACTION_DIM), out.shape
    assert torch.isfinite(out).all()
    runs = []
    cpu0 = time.process_time()
    for _ in range(iters):
        t0 = time.perf_counter()
        run()
        runs.append((time.perf_counter() - t0) * 1e3)
    print(json.dumps({
        "median_ms": statistics.median(runs),
        "runs": [round(r) for r in runs],
        "cpu_ms_per_run": (time.process_time() - cpu0) * 1e3 / iters,
        "model_rss_mb": model_rss,
        "load_peak_rss_mb": load_peak,
        "infer_peak_rss_mb": status_kb("VmHWM") / 1024,
        "params_m": sum(p.numel() for p in policy.parameters()) / 1e6,
        "prefix_tokens": len(CAMERAS) * (IMAGE // 14) ** 2 + prepared["observation.language.tokens"].shape[1],
        "torch": torch.__version__,
    }), flush=True)


def fmt(x, spec=".0f"):
    return "n/a" if x is None else format(x, spec)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--family", choices=("pi05", "pi0"), default="pi05")
    ap.add_argument("--small", action="store_true", help="toy widths and depths (a check of the tool)")
    ap.add_argument("--batch", default="1,4")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--iters", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--dtype", choices=("bfloat16", "float32"), default="bfloat16",
                    help="the config's dtype when writing: what save_pretrained stores")
    ap.add_argument("--write-checkpoint", type=Path, help="write the random checkpoint here")
    ap.add_argument("--checkpoint", type=Path, help="an already written checkpoint")
    ap.add_argument("--no-bench", action="store_true", help="only write the checkpoint")
    ap.add_argument("--kairos-bin", type=Path, help="the kairos binary (else PyTorch only)")
    ap.add_argument("--precisions", default="f32,bf16", help="`kairos predict --precision` values, in turn")
    ap.add_argument("--kairos-args", default="", help="more flags for `kairos predict`, e.g. '--kernels fast'")
    ap.add_argument("--torch-worker", type=int, metavar="B", help=argparse.SUPPRESS)
    ap.add_argument("--writer", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()

    if args.torch_worker is not None:
        torch_worker(args.checkpoint, args.small, args.torch_worker, args.threads, args.iters)
        return
    if args.writer is not None:
        write_checkpoint(args.family, args.small, args.dtype, args.writer)
        return
    if args.checkpoint is not None and args.write_checkpoint is not None:
        ap.error("--checkpoint and --write-checkpoint exclude each other")
    if args.no_bench and args.write_checkpoint is None:
        ap.error("--no-bench needs --write-checkpoint")
    batches = [int(b) for b in args.batch.split(",")]
    precisions = [p for p in args.precisions.split(",") if p]
    me = [sys.executable, str(Path(__file__).resolve())]
    t0 = time.perf_counter()

    tmp = None
    ckpt = args.checkpoint
    if ckpt is None:
        ckpt = args.write_checkpoint
        if ckpt is None:
            tmp = tempfile.TemporaryDirectory(prefix=f"{args.family}_base_random_")
            ckpt = Path(tmp.name)
        progress(t0, f"writing the {'toy' if args.small else 'base-shaped'} {args.family} checkpoint to {ckpt} ...")
        # A child process: the writer's memory is gone before anything is measured.
        small = ["--small"] if args.small else []
        subprocess.run([*me, "--family", args.family, "--dtype", args.dtype, *small, "--writer", str(ckpt)], check=True)
    if args.no_bench:
        return
    ckpt = ckpt.resolve()
    # LeRobot builds a toy checkpoint's modules only with the same size patches it was written with.
    embed = safetensors_header(ckpt / "model.safetensors")[EMBED_KEY]["shape"]
    size_flags = ["--small"] if embed[1] != GEMMA_2B_WIDTH else []
    try:
        bench(args, ckpt, batches, precisions, me, size_flags, t0)
    finally:
        if tmp is not None:
            tmp.cleanup()


def bench(args, ckpt, batches, precisions, me, size_flags, t0):
    kairos = None
    if args.kairos_bin:
        bin_ = shlex.quote(str(args.kairos_bin.resolve()))
        kairos = (f"{bin_} predict --model {{model}} --batch {{batch}} --threads {{threads}} "
                  f"--repeat {{iters}} --precision {{precision}} {args.kairos_args}")
    print(machine_line(f"torch threads {args.threads}, "), flush=True)
    results = {}
    for r in range(args.rounds):
        for b in batches:
            load = open("/proc/loadavg").read().split()[0]
            progress(t0, f"round {r + 1}, B={b} (load avg {load}): PyTorch ...")
            pt = run_json([*me, "--torch-worker", str(b), "--checkpoint", str(ckpt), "--threads", str(args.threads),
                           "--iters", str(args.iters), *size_flags], REPO)
            progress(t0, f"  PyTorch: runs {pt['runs']} ms, cpu {pt['cpu_ms_per_run']:.0f} ms/run, model RSS "
                         f"{pt['model_rss_mb']:.0f} MB, peak RSS {pt['child_peak_rss_mb']:.0f} MB "
                         f"(inference {pt['infer_peak_rss_mb']:.0f} MB)")
            kept = results.setdefault(b, {})
            if "torch" not in kept or pt["median_ms"] < kept["torch"]["median_ms"]:
                kept["torch"] = pt
            for p in precisions if kairos else []:
                progress(t0, f"  Kairos --precision {p} ...")
                ka = time_kairos(kairos, ckpt, b, args.threads, args.iters, REPO, precision=p)
                progress(t0, f"  Kairos {p}: {ka}")
                if p not in kept or ka["median_ms"] > kept[p]["median_ms"]:  # conservative for Kairos
                    kept[p] = ka
    any_pt = next(iter(results.values()))["torch"]
    print(f"# {args.family}{' (toy sizes)' if size_flags else ''}: {any_pt['params_m']:.1f} M parameters, "
          f"prefix {any_pt['prefix_tokens']} tokens, torch {any_pt['torch']}, checkpoint {ckpt}")
    head = "| batch | PyTorch ms | PyTorch CPU ms/run | PyTorch model RSS MB | PyTorch peak RSS MB |"
    rule = "|---:|---:|---:|---:|---:|"
    for p in precisions if kairos else []:
        head += (f" Kairos {p} ms | Kairos {p} CPU ms/run | {p} / PyTorch (target {TARGETS.get(p, '-')}) |"
                 f" Kairos {p} model RSS MB | Kairos {p} peak RSS MB |")
        rule += "---:|---:|---:|---:|---:|"
    print(head)
    print(rule)
    verdicts = []
    for b in batches:
        kept = results[b]
        pt = kept["torch"]
        row = (f"| {b} | {pt['median_ms']:.0f} | {pt['cpu_ms_per_run']:.0f} | {pt['model_rss_mb']:.0f} "
               f"| {pt['child_peak_rss_mb']:.0f} |")
        for p in precisions if kairos else []:
            ka = kept[p]
            ratio = ka["median_ms"] / pt["median_ms"]
            peak = ka.get("rss_mb", ka.get("child_peak_rss_mb"))
            row += (f" {ka['median_ms']:.0f} | {fmt(ka.get('cpu_ms_per_run'))} | {ratio:.2f} "
                    f"| {fmt(ka.get('model_rss_mb'))} | {fmt(peak)} |")
            if p in TARGETS:
                verdicts.append(f"B={b} {p}: {ratio:.2f}x {'meets' if ratio <= TARGETS[p] else 'misses'} "
                                f"<= {TARGETS[p]}x")
            if peak is not None:
                below = peak < pt["child_peak_rss_mb"]
                verdicts.append(f"B={b} {p}: peak RSS {peak:.0f} MB {'below' if below else 'not below'} "
                                f"PyTorch's {pt['child_peak_rss_mb']:.0f} MB")
        print(row)
    toy = " (toy sizes: a check of the tool, not a result)" if size_flags else ""
    for v in verdicts:
        print(f"# {v}{toy}")


if __name__ == "__main__":
    main()
