#!/usr/bin/env python3
"""Regenerate the SmolVLA golden files that `engine/tests/smolvla_parity.rs` checks against.

    python3 engine/tools/reference.py            # writes engine/tests/golden/smolvla_small/

It instantiates LeRobot 0.6.1's own `SmolVLAPolicy` (VLM + action expert, LeRobot's code
unchanged) with a *small* random configuration, runs `predict_action_chunk` on a fixed batch
of three observations with fixed noise, and saves:

- `config.json`: the policy config as LeRobot writes it (`PreTrainedConfig._save_pretrained`).
- `vlm_config.json`: the SmolVLM config the VLM was built from (normally fetched from the hub by
  `vlm_model_name`; written locally because the test config is not on the hub).
- `model.safetensors`: the expert's tensors under LeRobot's parameter names (`model.vlm_with_expert.
  lm_expert.*`, `model.state_proj.*`, `model.action_*`); the VLM's own weights are left out.
- `io.safetensors`: the expert's inputs (the prefix KV cache LeRobot's VLM filled, per layer, in
  LeRobot's [batch, seq, kv_heads, head_dim] layout, post-RoPE; the prefix pad mask; the padded
  state; the noise) and LeRobot's outputs (state_proj(state), the velocity of every Euler step and
  the final chunk), plus the same outputs recomputed in float64 (`*_f64`) so the test can tell
  LeRobot's own float32 rounding from a real mismatch.

With `--rtc` it writes real-time chunking goldens on `engine/tests/fixtures/smolvla_tiny`
instead (`golden/rtc.safetensors`, described in `golden/rtc.json`): the checkpoint and its
processors loaded with LeRobot's own `from_pretrained`, the fixture's `pair` observations, a
previous chunk (LeRobot's plain chunk for the same observations with other noise, normalised, of
which the robot executed 2 actions: the queue's leftover, LeRobot's `prev_chunk_left_over`),
and for each prefix schedule (`linear`, `exp`) and inference delay `d` in {0, 3, 7}:
`predict_action_chunk` with `rtc_config` (`RTCProcessor.denoise_step` unchanged, max guidance
weight 10, execution horizon 10), recording the guided velocity each Euler step used, the prefix
weights, and the chunk before and after the postprocessor. One more case runs the paper's
guidance with the true vector–Jacobian product (`rtc_vjp`: the same formula with the sample
marked as needing a gradient before the velocity is computed; LeRobot does not ship it, so this
one is the script's own, on LeRobot's modules).

The script creates `<repo>/.venv-lerobot` with the pinned LeRobot itself (see `lerobot_env.py`).
"""

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from lerobot_env import REPO, ensure_venv  # noqa: E402

ensure_venv()

import torch  # noqa: E402
from safetensors.torch import save_file  # noqa: E402

from smolvla_common import patch_hub, rescale_weights  # noqa: E402

# Small configuration: every structural feature of the real expert at toy width.
# The real SmolVLM2-500M text config is hidden 960, 15 query / 5 KV heads of 64 (GQA 3),
# 16 kept layers (expert 720); here hidden 96 (expert 72), 6 / 2 heads of 16 (GQA 3), 4 layers
# (2 self-, 2 cross-attention). As in the real model, heads x head_dim != expert hidden.
TEXT_CONFIG = dict(
    model_type="llama",
    hidden_size=96,
    intermediate_size=128,
    num_hidden_layers=4,
    num_attention_heads=6,
    num_key_value_heads=2,
    head_dim=16,
    rms_norm_eps=1e-5,
    vocab_size=64,
    max_position_embeddings=256,
    rope_theta=100000.0,
    pad_token_id=0,
    tie_word_embeddings=False,
)
VISION_CONFIG = dict(
    hidden_size=32,
    intermediate_size=64,
    num_hidden_layers=1,
    num_attention_heads=2,
    image_size=32,
    patch_size=8,
    num_channels=3,
)
CHUNK = 16
STATE_DIM = 7
ACTION_DIM = 6
LANG_LEN = 12
LANG_VALID = [12, 7, 3]  # per batch element: prefixes of different real lengths
SEED = 20261121
CHUNK_TINY = 16  # smolvla_tiny's chunk


def build_policy():
    from transformers import SmolVLMConfig

    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    vlm_config = SmolVLMConfig(text_config=dict(TEXT_CONFIG), vision_config=dict(VISION_CONFIG), scale_factor=2)
    patch_hub(vlm_config)  # the hub is not reachable for this config: hand LeRobot the local one

    cfg = SmolVLAConfig(
        chunk_size=CHUNK,
        n_action_steps=CHUNK,
        num_steps=10,
        max_state_dim=32,
        max_action_dim=32,
        resize_imgs_with_padding=(32, 32),
        tokenizer_max_length=LANG_LEN,
        num_vlm_layers=TEXT_CONFIG["num_hidden_layers"],
        self_attn_every_n_layers=2,
        expert_width_multiplier=0.75,
        attention_mode="cross_attn",
        load_vlm_weights=False,
        device="cpu",
        input_features={
            "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(STATE_DIM,)),
            "observation.images.cam0": PolicyFeature(type=FeatureType.VISUAL, shape=(3, 32, 32)),
            "observation.images.cam1": PolicyFeature(type=FeatureType.VISUAL, shape=(3, 32, 32)),
        },
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(ACTION_DIM,))},
    )
    policy = SmolVLAPolicy(cfg)
    return policy, cfg, vlm_config


def make_batch(gen):
    b = len(LANG_VALID)
    tokens = torch.randint(3, TEXT_CONFIG["vocab_size"], (b, LANG_LEN), generator=gen)
    mask = torch.zeros(b, LANG_LEN, dtype=torch.bool)
    for i, n in enumerate(LANG_VALID):
        mask[i, :n] = True
        tokens[i, n:] = 0
    return {
        "observation.state": torch.randn(b, STATE_DIM, generator=gen),
        "observation.images.cam0": torch.rand(b, 3, 32, 32, generator=gen),
        "observation.images.cam1": torch.rand(b, 3, 32, 32, generator=gen),
        "observation.language.tokens": tokens,
        "observation.language.attention_mask": mask,
    }


def run(policy, batch, noise):
    """LeRobot's predict_action_chunk, recording what the expert sees and returns."""
    model = policy.model
    record = {"v": [], "t": []}
    denoise_step = model.denoise_step

    def recording_denoise_step(**kw):
        record["prefix_pad_masks"] = kw["prefix_pad_masks"]
        record["cache"] = kw["past_key_values"]
        v = denoise_step(**kw)
        record["v"].append(v.clone())
        record["t"].append(kw["timestep"].clone())
        return v

    model.denoise_step = recording_denoise_step
    try:
        policy.reset()
        chunk = policy.predict_action_chunk(dict(batch), noise=noise)
        # The full padded chunk: predict_action_chunk cuts to the real action dim.
        x = noise.clone()
        for v in record["v"]:
            x = x + (-1.0 / policy.config.num_steps) * v
    finally:
        model.denoise_step = denoise_step
    return chunk, x, record


@torch.no_grad()
def denoise_f64(policy, record, noise):
    """The same expert on the same prefix cache, in float64 (LeRobot's modules, double weights)."""
    from lerobot.policies.common.flow_matching import euler_integrate

    model = policy.model.double()
    # denoise_step casts the expert output to float32 before action_out_proj (openpi's upcast), so
    # that last projection stays float32; its rounding is ~1e-7 relative, far below the tolerances.
    model.action_out_proj.float()
    cache = record["cache"]
    for layer in cache.layers:
        layer.keys = layer.keys.double()
        layer.values = layer.values.double()
    vs = []

    def step(x, t):
        v = model.denoise_step(
            x_t=x, prefix_pad_masks=record["prefix_pad_masks"], past_key_values=cache, timestep=t
        )
        vs.append(v)
        return v

    x = euler_integrate(step, noise.double(), policy.config.num_steps)
    policy.float()
    return x, torch.stack(vs)


RTC_DELAYS = [0, 3, 7]
RTC_EXECUTED = 2  # actions of the previous chunk the robot executed before the capture
RTC_EXECUTION_HORIZON = 10
RTC_MAX_GUIDANCE_WEIGHT = 10.0
RTC_VJP_CASE = ("linear", 3)


def vjp_denoise_step(processor, x_t, prev, inference_delay, time, denoise, execution_horizon):
    """`rtc_vjp`: LeRobot's `RTCProcessor.denoise_step` with one change, the paper's guidance:
    the sample needs a gradient before the velocity is computed, so the correction is the
    weighted error pulled back through the velocity network (`err - J^T (time * err)`)."""
    tau = 1 - time
    x_t = x_t.clone().detach()
    batch, chunk, dim = x_t.shape
    eh = min(execution_horizon, prev.shape[1])
    padded = torch.zeros(batch, chunk, dim)
    padded[:, : prev.shape[1], : prev.shape[2]] = prev
    weights = processor.get_prefix_weights(inference_delay, eh, chunk).unsqueeze(0).unsqueeze(-1)
    with torch.enable_grad():
        x_t.requires_grad_(True)
        v_t = denoise(x_t)
        x1_t = x_t - time * v_t
        err = (padded - x1_t) * weights
        correction = torch.autograd.grad(x1_t, x_t, err.clone().detach())[0]
    max_w = torch.as_tensor(processor.rtc_config.max_guidance_weight)
    tau_t = torch.as_tensor(tau)
    sq = (1 - tau_t) ** 2
    inv_r2 = (sq + tau_t**2) / sq
    c = torch.nan_to_num((1 - tau_t) / tau_t, posinf=max_w)
    w = torch.minimum(torch.nan_to_num(c * inv_r2, posinf=max_w), max_w)
    return (v_t - w * correction).detach()


def rtc_goldens(fixture: Path):
    """The real-time chunking goldens (module docs, `--rtc`)."""
    from safetensors.torch import load_file

    from lerobot.configs.types import RTCAttentionSchedule
    from lerobot.policies.rtc.configuration_rtc import RTCConfig
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
    from lerobot.processor import PolicyProcessorPipeline
    from lerobot.processor.converters import policy_action_to_transition, transition_to_policy_action

    from transformers import PreTrainedTokenizerFast, SmolVLMConfig

    torch.set_num_threads(2)
    # The fixture's own VLM config and tokenizer, handed to LeRobot instead of the hub's.
    vlm_config = SmolVLMConfig.from_dict(json.loads((fixture / "vlm_config.json").read_text()))
    tokenizer = PreTrainedTokenizerFast(
        tokenizer_file=str(fixture / "tokenizer.json"),
        pad_token="<|im_end|>",
        eos_token="<|im_end|>",
        bos_token="<|im_start|>",
    )
    patch_hub(vlm_config, tokenizer)
    policy = SmolVLAPolicy.from_pretrained(fixture).eval()
    pre = PolicyProcessorPipeline.from_pretrained(fixture, config_filename="policy_preprocessor.json")
    post = PolicyProcessorPipeline.from_pretrained(
        fixture,
        config_filename="policy_postprocessor.json",
        to_transition=policy_action_to_transition,
        to_output=transition_to_policy_action,
    )
    golden = load_file(str(fixture / "golden/goldens.safetensors"))
    meta = json.loads((fixture / "golden/meta.json").read_text())
    raw = {k.removeprefix("pair.raw."): v for k, v in golden.items() if k.startswith("pair.raw.")}
    obs = {k: (v.float() / 255).permute(0, 3, 1, 2).contiguous() for k, v in raw.items() if k != "state"}
    obs["observation.state"] = raw["state"]
    obs["task"] = list(meta["cases"]["pair"]["tasks"])
    batch = pre(obs)
    noise = golden["pair.noise"]
    gen = torch.Generator().manual_seed(SEED + 7)
    prev_noise = torch.randn(noise.shape, generator=gen)
    with torch.no_grad():
        policy.reset()
        prev_norm = policy.predict_action_chunk(dict(batch), noise=prev_noise)
    leftover_norm = prev_norm[:, RTC_EXECUTED:].contiguous()
    leftover = post(leftover_norm.clone())
    out = {
        "noise": noise.contiguous(),
        "prev_actions_norm": prev_norm.contiguous(),
        "leftover_norm": leftover_norm,
        "leftover": leftover.contiguous(),
    }
    schedules = {"linear": RTCAttentionSchedule.LINEAR, "exp": RTCAttentionSchedule.EXP}
    cases = [(name, d, False) for name in schedules for d in RTC_DELAYS] + [(*RTC_VJP_CASE, True)]
    for name, d, vjp in cases:
        policy.config.rtc_config = RTCConfig(
            prefix_attention_schedule=schedules[name],
            max_guidance_weight=RTC_MAX_GUIDANCE_WEIGHT,
            execution_horizon=RTC_EXECUTION_HORIZON,
        )
        policy.init_rtc_processor()
        processor = policy.rtc_processor
        guided = []
        original = processor.denoise_step

        def recording(**kw):
            if vjp:
                v = vjp_denoise_step(
                    processor,
                    kw["x_t"],
                    kw["prev_chunk_left_over"],
                    kw["inference_delay"],
                    kw["time"],
                    kw["original_denoise_step_partial"],
                    kw["execution_horizon"],
                )
            else:
                v = original(**kw)
            guided.append(v.detach().clone())
            return v

        processor.denoise_step = recording
        try:
            with torch.no_grad():
                policy.reset()
                actions_norm = policy.predict_action_chunk(
                    dict(batch),
                    noise=noise,
                    inference_delay=d,
                    prev_chunk_left_over=leftover_norm,
                    execution_horizon=RTC_EXECUTION_HORIZON,
                )
        finally:
            processor.denoise_step = original
        key = f"{'rtc_vjp' if vjp else 'rtc'}.{name}.d{d}"
        eh = min(RTC_EXECUTION_HORIZON, leftover_norm.shape[1])
        out[f"{key}.weights"] = processor.get_prefix_weights(d, eh, CHUNK_TINY).contiguous()
        out[f"{key}.velocities"] = torch.stack(guided).contiguous()
        out[f"{key}.actions_norm"] = actions_norm.contiguous()
        out[f"{key}.actions"] = post(actions_norm.clone()).contiguous()
    import lerobot

    save_file(out, str(fixture / "golden/rtc.safetensors"), metadata={"lerobot": lerobot.__version__})
    described = {
        "generator": "engine/tools/reference.py --rtc",
        "versions": {"lerobot": lerobot.__version__, "torch": torch.__version__},
        "case": "pair (golden/goldens.safetensors: raw images, state, tasks, noise)",
        "executed": RTC_EXECUTED,
        "execution_horizon": RTC_EXECUTION_HORIZON,
        "max_guidance_weight": RTC_MAX_GUIDANCE_WEIGHT,
        "delays": RTC_DELAYS,
        "schedules": list(schedules),
        "vjp_case": {"schedule": RTC_VJP_CASE[0], "delay": RTC_VJP_CASE[1]},
        "tensors": {
            "noise": "[batch, chunk, max_action_dim] f32, the Euler loop's initial x (pair.noise)",
            "prev_actions_norm": "[batch, chunk, action_dim] f32, the previous chunk (normalised)",
            "leftover_norm": f"[batch, chunk - {RTC_EXECUTED}, action_dim] f32, LeRobot's prev_chunk_left_over",
            "leftover": "the same after the postprocessor (the robot's units: what Kairos' guidance prefix holds)",
            "rtc.{schedule}.d{d}.weights": "[chunk] f32, get_prefix_weights(d, min(execution_horizon, leftover), chunk)",
            "rtc.{schedule}.d{d}.velocities": "[steps, batch, chunk, max_action_dim] f32, the guided velocity each step used",
            "rtc.{schedule}.d{d}.actions_norm": "[batch, chunk, action_dim] f32, predict_action_chunk's output",
            "rtc.{schedule}.d{d}.actions": "the same after the postprocessor",
            "rtc_vjp.*": "as rtc.*, with the true vector-Jacobian product (vjp_denoise_step)",
        },
    }
    (fixture / "golden/rtc.json").write_text(json.dumps(described, indent=1) + "\n")
    print(f"wrote {fixture / 'golden/rtc.safetensors'} ({len(out)} tensors)")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=REPO / "engine/tests/golden/smolvla_small")
    ap.add_argument("--rtc", action="store_true", help="write the real-time chunking goldens instead")
    ap.add_argument("--fixture", type=Path, default=REPO / "engine/tests/fixtures/smolvla_tiny")
    args = ap.parse_args()
    if args.rtc:
        rtc_goldens(args.fixture)
        return
    args.out.mkdir(parents=True, exist_ok=True)

    torch.manual_seed(SEED)
    policy, cfg, vlm_config = build_policy()
    policy.eval()
    rescale_weights(policy, SEED)

    gen = torch.Generator().manual_seed(SEED + 1)
    batch = make_batch(gen)
    noise = torch.randn(len(LANG_VALID), CHUNK, cfg.max_action_dim, generator=gen)

    with torch.no_grad():
        chunk, x_full, record = run(policy, batch, noise)
        state = policy.prepare_state(batch)
        state_emb = policy.model.state_proj(state)
    assert torch.equal(chunk, x_full[:, :, :ACTION_DIM]), "replayed Euler sum differs from LeRobot's chunk"
    cache = record["cache"]
    prefix_len = record["prefix_pad_masks"].shape[1]
    assert all(layer.keys.shape[2] == prefix_len for layer in cache.layers)

    io = {
        "prefix_pad_mask": record["prefix_pad_masks"].to(torch.uint8).contiguous(),
        "state": state.contiguous(),
        "noise": noise.contiguous(),
        "state_emb": state_emb.contiguous(),
        "timesteps": torch.stack(record["t"])[:, 0].contiguous(),
        "velocities": torch.stack(record["v"]).contiguous(),
        "actions": x_full.contiguous(),
    }
    for i, layer in enumerate(cache.layers):
        # DynamicCache holds [batch, kv_heads, seq, head_dim]; the module works in [batch, seq, heads, dim].
        io[f"prefix.{i}.key"] = layer.keys.transpose(1, 2).contiguous()
        io[f"prefix.{i}.value"] = layer.values.transpose(1, 2).contiguous()

    actions_f64, velocities_f64 = denoise_f64(policy, record, noise)
    io["actions_f64"] = actions_f64.contiguous()
    io["velocities_f64"] = velocities_f64.contiguous()
    f32_err = (x_full.double() - actions_f64).abs().max().item()
    v_err = (torch.stack(record["v"]).double() - velocities_f64).abs().max().item()

    keep = ("model.vlm_with_expert.lm_expert.", "model.state_proj.", "model.action_")
    weights = {k: v.contiguous() for k, v in policy.state_dict().items() if k.startswith(keep)}
    save_file(weights, str(args.out / "model.safetensors"))
    save_file(io, str(args.out / "io.safetensors"), metadata={"lerobot": "0.6.1", "torch": torch.__version__})
    cfg._save_pretrained(args.out)
    (args.out / "vlm_config.json").write_text(vlm_config.to_json_string())
    meta = {
        "lerobot": "0.6.1",
        "torch": torch.__version__,
        "batch": len(LANG_VALID),
        "prefix_len": prefix_len,
        "prefix_valid": record["prefix_pad_masks"].sum(1).tolist(),
        "lerobot_f32_vs_f64_max_abs_actions": f32_err,
        "lerobot_f32_vs_f64_max_abs_velocity": v_err,
        "max_abs_action": x_full.abs().max().item(),
        "max_abs_velocity": torch.stack(record["v"]).abs().max().item(),
    }
    (args.out / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    print(json.dumps(meta, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
