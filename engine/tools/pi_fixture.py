#!/usr/bin/env python3
"""Regenerate `engine/tests/fixtures/pi0_tiny/` and `pi05_tiny/`: small random π0 and π0.5
checkpoints as LeRobot 0.6.1 saves them, plus golden intermediates of LeRobot's own inference.

    python3 engine/tools/pi_fixture.py            # writes both fixtures
    python3 engine/tools/pi_fixture.py --only pi05

Each directory is what a user's fine-tuned π0 / π0.5 looks like, at toy size:

- `config.json`, `model.safetensors`: `PI0Policy` / `PI05Policy.save_pretrained` (float32).
- `policy_preprocessor.json`, `policy_postprocessor.json` and the stats files their steps name
  in `state_file`: `make_pi0_pre_post_processors` / `make_pi05_pre_post_processors`, saved with
  `save_pretrained`. π0: state and action MEAN_STD (its default); π0.5: QUANTILES (its default).
  The preprocessor's rename map sends `observation.images.top` to `observation.images.base`.
- `tokenizer.json` + `tokenizer_config.json`: a Gemma-style BPE (spaces as `▁`, byte fallback,
  `<bos>` prepended by the post-processor, `<pad>` id 0) trained with the `tokenizers` library
  on a fixed corpus (`pi_common.write_tokenizer`); it stands in for
  `google/paligemma-3b-pt-224`'s, which LeRobot fetches.

LeRobot hard-codes the architecture: `get_gemma_config` knows only `gemma_2b` and `gemma_300m`,
and `PaliGemmaWithExpertModel` builds SigLIP so400m/14 and a 257 152-token vocabulary. To make
a toy model, this script replaces exactly those three things and nothing else
(`pi_common.patch_lerobot` with `pi_common.ToySizes`):
`get_gemma_config` returns small widths (8 query heads and 1 KV head as in every variant; 8 is
also hard-coded in LeRobot's joint forward), and the two model constructors get a small SigLIP
(16 heads as so400m; width 64) and a small vocabulary. The config still says `gemma_2b` /
`gemma_300m` (LeRobot accepts no other names): a loader must take the sizes from the tensors.
Every module's code runs unchanged; the hub is never reached.

`golden/` holds the cases run through LeRobot's inference path (u8 -> [0,1] CHW, the
preprocessor, `predict_action_chunk` with fixed noise, the postprocessor), with intermediates
recorded by wrapping LeRobot's own functions (`_preprocess_images`, `embed_image`, the SigLIP
tower, `embed_prefix`, the prefix pass of `paligemma_with_expert.forward`, `denoise_step`):
nothing is re-implemented. `golden/meta.json` describes every tensor. Each float golden `X`
except images also has `X.f64`: the same LeRobot code in float64 (weights and inputs in double;
LeRobot's and transformers' explicit float32 casts redirected to float64, see
`smolvla_common.float64_casts` and `tensor_float_is_double`), so a test can bound LeRobot's own
float32 rounding (`meta.json` -> `lerobot_f32_vs_f64`).

Cases (`golden/meta.json` -> `cases`):
- `pair`: 2 observations; `top` (renamed to `base`) 43x71 u8 images (resized with centred
  padding into 56x56) and `wrist` 56x56 (already the model's size: not resized); a long task
  (truncated by the tokenizer's max length) and a short one (padded to it); states with values
  beyond the normaliser's range (π0.5 writes bins -1 and 255 for them).
- `missing`: 1 observation without `wrist`: LeRobot fills it with a masked all -1 image.
The config's `empty_cameras: 1` adds a third, always masked, camera slot.

The checkpoint is reloaded with LeRobot's own `from_pretrained` (policy and both processors, the
same patches in place) and re-run: the goldens must be bit-identical, so the files are exactly
what LeRobot loads. Seeded: rerunning writes the same tensors on the same torch build.
"""

import argparse
import contextlib
import copy
import json
import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from lerobot_env import REPO, ensure_venv  # noqa: E402

ensure_venv()

import torch  # noqa: E402
from safetensors.torch import save_file  # noqa: E402

from pi_common import ToySizes, hf_tokenizer, patch_lerobot, policy_classes, write_tokenizer  # noqa: E402
from smolvla_common import feature_stats, float64_casts, rescale_weights  # noqa: E402

SEED = 20261129
TOY = ToySizes()
TINY_GEMMA = TOY.gemma
TINY_SIGLIP = TOY.siglip
VOCAB = TOY.vocab
IMAGE = 56  # 4 x 4 patches = 16 tokens per camera (224 -> 256 at full size)
CHUNK = 12
STATE_DIM = 7
ACTION_DIM = 6
CAMERAS = ("observation.images.base", "observation.images.wrist")
RENAME = {"observation.images.top": "observation.images.base"}
LONG_TASK = "pick up the red cube from the left bin, rotate it and place it gently on the blue plate"
SHORT_TASK = "pick up the cube"
MISSING_TASK = "put the blue block on the plate"
FAMILIES = {
    # name: (LeRobot policy type, tokenizer max_length)
    "pi0": ("pi0", 12),
    "pi05": ("pi05", 40),
}


def build(family, tokenizer):
    from lerobot.configs.types import FeatureType, PolicyFeature

    policy_type, max_len = FAMILIES[family]
    Config, Policy, make_processors = policy_classes(policy_type)

    cfg = Config(
        chunk_size=CHUNK,
        n_action_steps=CHUNK,
        image_resolution=(IMAGE, IMAGE),
        empty_cameras=1,
        tokenizer_max_length=max_len,
        device="cpu",
        input_features={
            "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(STATE_DIM,)),
            CAMERAS[0]: PolicyFeature(type=FeatureType.VISUAL, shape=(3, 43, 71)),
            CAMERAS[1]: PolicyFeature(type=FeatureType.VISUAL, shape=(3, IMAGE, IMAGE)),
        },
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(ACTION_DIM,))},
    )
    torch.manual_seed(SEED)
    policy = Policy(cfg).eval()
    rescale_weights(policy, SEED + (0 if policy_type == "pi0" else 1))

    gen = torch.Generator().manual_seed(SEED + 7)
    dataset_stats = {
        "observation.state": feature_stats(gen, STATE_DIM, 2.0),
        "action": feature_stats(gen, ACTION_DIM, 1.5),
    }
    pre, post = make_processors(cfg, dataset_stats=dataset_stats)
    pre.steps[0].rename_map = dict(RENAME)
    return policy, pre, post, Policy, dataset_stats["observation.state"]


def make_cases(state_stats):
    """Raw observations as a robot gives them: u8 HWC images, f32 state, task text."""
    gen = torch.Generator().manual_seed(SEED + 1)

    def image(h, w):
        yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
        base = torch.stack([xx * 255 / max(w - 1, 1), yy * 255 / max(h - 1, 1), (xx + yy) * 127 / (h + w)], -1)
        noisy = base + 40 * torch.randn(h, w, 3, generator=gen)
        return noisy.clamp(0, 255).round().to(torch.uint8)

    mean, std = state_stats["mean"], state_stats["std"]
    state = mean + 1.5 * std * torch.randn(2, STATE_DIM, generator=gen)
    # Beyond the normaliser's range on both sides: π0.5's state bins -1 and 255.
    state[0, 1] = mean[1] - 4 * std[1]
    state[1, 2] = mean[2] + 4 * std[2]
    pair = {
        "tasks": [LONG_TASK, SHORT_TASK],
        "images": {
            "observation.images.top": torch.stack([image(43, 71), image(43, 71)]),
            CAMERAS[1]: torch.stack([image(IMAGE, IMAGE), image(IMAGE, IMAGE)]),
        },
        "state": state,
    }
    missing = {
        "tasks": [MISSING_TASK],
        "images": {"observation.images.top": image(43, 71)[None]},
        "state": mean + std * torch.randn(1, STATE_DIM, generator=gen),
    }
    noise = {
        "pair": torch.randn(2, CHUNK, 32, generator=gen),
        "missing": torch.randn(1, CHUNK, 32, generator=gen),
    }
    return {"pair": pair, "missing": missing}, noise


def to_policy_input(case, dtype):
    """LeRobot's `prepare_observation_for_inference`, batched: u8 HWC -> float [0,1] CHW."""
    obs = {k: (v.to(dtype) / 255).permute(0, 3, 1, 2).contiguous() for k, v in case["images"].items()}
    obs["observation.state"] = case["state"].to(dtype)
    obs["task"] = list(case["tasks"])
    return obs


class Recorder:
    """Wraps LeRobot's functions on one policy and records what they return (nothing changes)."""

    def __init__(self, policy, time_dtype=None):
        self.rec = rec = {}
        model = policy.model
        pwe = model.paligemma_with_expert
        self.saved = [
            (policy, "_preprocess_images", policy._preprocess_images),
            (pwe, "embed_image", pwe.embed_image),
            (model, "embed_prefix", model.embed_prefix),
            (pwe, "forward", pwe.forward),
            (model, "denoise_step", model.denoise_step),
        ]
        if hasattr(policy, "prepare_state"):
            self.saved.append((policy, "prepare_state", policy.prepare_state))

            def prepare_state(batch):
                state = self.saved[5][2](batch)
                rec["state_padded"] = state.clone()
                return state

            policy.prepare_state = prepare_state

        def preprocess_images(batch):
            images, masks = self.saved[0][2](batch)
            rec["images"] = [i.clone() for i in images]
            rec["image_masks"] = [m.clone() for m in masks]
            return images, masks

        def embed_image(image):
            out = self.saved[1][2](image)
            rec.setdefault("image_embs", []).append(out.clone())
            return out

        def embed_prefix(*a, **k):
            embs, pad, att = self.saved[2][2](*a, **k)
            rec["prefix_embs"] = embs.clone()
            rec["prefix_pad_mask"] = pad.clone()
            rec["prefix_att_mask"] = att.clone()
            return embs, pad, att

        def forward(**kw):
            out, cache = self.saved[3][2](**kw)
            if kw["inputs_embeds"][1] is None:  # the prefix pass, which fills the KV cache
                rec["prefix_positions"] = kw["position_ids"].clone()
                # DynamicCache holds [batch, kv_heads, seq, head_dim]; store [batch, seq, kv_heads, head_dim].
                rec["keys"] = [layer.keys.transpose(1, 2).clone() for layer in cache.layers]
                rec["values"] = [layer.values.transpose(1, 2).clone() for layer in cache.layers]
            return out, cache

        def denoise_step(**kw):
            if time_dtype is not None:
                kw["timestep"] = kw["timestep"].to(time_dtype)
            v = self.saved[4][2](**kw)
            rec.setdefault("velocities", []).append(v.clone())
            return v

        policy._preprocess_images = preprocess_images
        pwe.embed_image = embed_image
        model.embed_prefix = embed_prefix
        pwe.forward = forward
        model.denoise_step = denoise_step
        vision = pwe.paligemma.model.vision_tower
        self.hook = vision.register_forward_hook(
            lambda _m, _i, out: rec.setdefault("vision", []).append(out.last_hidden_state.clone())
        )

    def close(self):
        for obj, name, _ in self.saved:
            delattr(obj, name)  # back to the class attribute
        self.hook.remove()


def infer(policy, pre, post, case, noise, dtype):
    """One LeRobot inference: preprocessor, predict_action_chunk, postprocessor; all recorded."""
    batch = pre(to_policy_input(case, dtype))
    # The Euler loop makes each time a float32 (`euler_integrate`); that value is the model's
    # input, so the float64 reference widens it rather than using the exact 1 + k dt.
    rec = Recorder(policy, time_dtype=dtype if dtype != torch.float32 else None)
    try:
        policy.reset()
        actions_norm = policy.predict_action_chunk(dict(batch), noise=noise.to(dtype))
    finally:
        rec.close()
    actions = post(actions_norm.clone())
    r = rec.rec
    r["tokens"] = batch["observation.language.tokens"]
    r["token_mask"] = batch["observation.language.attention_mask"]
    r["state_norm"] = batch["observation.state"]
    r["prompts"] = list(batch["task"])
    r["actions_norm"] = actions_norm
    r["actions"] = actions
    return r


def flatten(case_name, case, rec, noise):
    """Golden tensors and their descriptions for one case."""
    out, desc = {}, {}

    def put(name, t, layout, note=""):
        key = f"{case_name}.{name}"
        if t.dtype == torch.bool:
            t = t.to(torch.uint8)
        out[key] = t.contiguous()
        desc[key] = {"shape": list(t.shape), "dtype": str(t.dtype).removeprefix("torch."), "layout": layout}
        if note:
            desc[key]["note"] = note

    for k, img in case["images"].items():
        put(f"raw.{k}", img, "[batch, height, width, rgb] u8, as the robot sends it (key before the rename map)")
    put("raw.state", case["state"], "[batch, state_dim] f32, before normalisation")
    put("noise", noise, "[batch, chunk, max_action_dim] f32, the initial x of the Euler loop")
    put("tokens", rec["tokens"], "[batch, max_length] i64, the tokenizer's ids (padded to max_length, right)")
    put("token_mask", rec["token_mask"], "[batch, max_length] u8, 1 = real token")
    put("state_norm", rec["state_norm"], "[batch, state_dim] f32, after the preprocessor's normaliser")
    if "state_padded" in rec:
        put("state_padded", rec["state_padded"], "[batch, max_state_dim] f32, state_norm zero-padded (prepare_state)")
    for i, (img, m) in enumerate(zip(rec["images"], rec["image_masks"], strict=True)):
        put(f"image.{i}", img, "[batch, 3, H, W] f32 in [-1,1]: resize_with_pad_torch (centred, 0 pad) then "
            "x*2-1; slot i in LeRobot's order (present cameras in config order, then every missing one)")
        put(f"image_mask.{i}", m, "[batch] u8, 0 = missing camera (all -1 image)")
    for i, v in enumerate(rec["vision"]):
        put(f"vision.{i}", v, "[batch, patches, vision_hidden] f32, SigLIP last_hidden_state (after post_layernorm)")
    for i, c in enumerate(rec["image_embs"]):
        put(f"image_emb.{i}", c, "[batch, patches, vlm_width] f32, multi_modal_projector(vision.i) (embed_image)")
    put("prefix_embs", rec["prefix_embs"], "[batch, prefix_len, vlm_width] f32: per camera slot image_emb, "
        "then language embeddings (embed_tokens x sqrt(width), the scaled embedding)")
    put("prefix_pad_mask", rec["prefix_pad_mask"], "[batch, prefix_len] u8, 1 = valid token")
    put("prefix_att_mask", rec["prefix_att_mask"], "[batch, prefix_len] u8, LeRobot's att_masks (all 0: prefix-LM)")
    put("prefix_positions", rec["prefix_positions"], "[batch, prefix_len] i64, cumsum(pad_mask) - 1")
    for i, (k, v) in enumerate(zip(rec["keys"], rec["values"], strict=True)):
        note = "compare only where prefix_pad_mask is 1: padded positions hold LeRobot's values for pad tokens"
        put(f"layer.{i}.key", k, "[batch, prefix_len, kv_heads, head_dim] f32, post-RoPE", note)
        put(f"layer.{i}.value", v, "[batch, prefix_len, kv_heads, head_dim] f32", note)
    put("velocities", torch.stack(rec["velocities"]), "[steps, batch, chunk, max_action_dim] f32, each denoise_step's v")
    put("actions_norm", rec["actions_norm"], "[batch, chunk, action_dim] f32, predict_action_chunk's output (normalised)")
    put("actions", rec["actions"], "[batch, chunk, action_dim] f32, after the postprocessor (unnormalised)")
    return out, desc


@contextlib.contextmanager
def tensor_float_is_double():
    """`Tensor.float()` returns float64 inside: PiGemmaRMSNorm and Gemma's RoPE call `.float()`
    on purpose (f32 statistics), which a float64 reference must not round to float32."""
    saved = torch.Tensor.float
    torch.Tensor.float = lambda self, *a, **k: self.to(torch.float64)
    try:
        yield
    finally:
        torch.Tensor.float = saved


def f64_pass(policy, pre, post, case, noise):
    """The same LeRobot inference in float64."""
    import lerobot.policies.common.vla_utils as vla_utils
    import lerobot.policies.pi0.modeling_pi0 as m0
    import lerobot.policies.pi05.modeling_pi05 as m05
    import lerobot.policies.pi_gemma as pg
    import transformers.models.gemma.modeling_gemma as gemma
    import transformers.models.siglip.modeling_siglip as siglip

    policy64 = copy.deepcopy(policy).double()
    pre64, post64 = copy.deepcopy(pre), copy.deepcopy(post)
    with float64_casts(m0, m05, pg, vla_utils, gemma, siglip), tensor_float_is_double():
        return infer(policy64, pre64, post64, case, noise, torch.float64)


def write_pngs(out_dir: Path, case_name, case):
    from PIL import Image

    names = []
    for k, imgs in case["images"].items():
        for b, img in enumerate(imgs):
            name = f"{case_name}.{b}.{k.rsplit('.', 1)[-1]}.png"
            Image.fromarray(img.numpy()).save(out_dir / name)
            names.append(name)
    return names


def write_fixture(family, out: Path):
    if out.exists():
        shutil.rmtree(out)
    (out / "golden").mkdir(parents=True)

    write_tokenizer(out / "tokenizer.json")
    tokenizer = hf_tokenizer(out / "tokenizer.json")
    patch_lerobot(tokenizer, TOY)
    policy, pre, post, Policy, state_stats = build(family, tokenizer)
    policy.save_pretrained(out)
    pre.save_pretrained(out)
    post.save_pretrained(out)

    # Reload everything from disk with LeRobot's own loaders: the goldens come from these files.
    from lerobot.processor import PolicyProcessorPipeline
    from lerobot.processor.converters import policy_action_to_transition, transition_to_policy_action

    loaded = Policy.from_pretrained(out).eval()
    for (k, v), (k2, v2) in zip(policy.state_dict().items(), loaded.state_dict().items(), strict=True):
        assert k == k2 and torch.equal(v, v2), f"reloaded tensor {k} differs"
    pre_l = PolicyProcessorPipeline.from_pretrained(out, config_filename="policy_preprocessor.json")
    post_l = PolicyProcessorPipeline.from_pretrained(
        out,
        config_filename="policy_postprocessor.json",
        to_transition=policy_action_to_transition,
        to_output=transition_to_policy_action,
    )

    cases, noises = make_cases(state_stats)
    tensors, described, errors, case_meta = {}, {}, {}, {}
    for name, case in cases.items():
        noise = noises[name]
        rec = infer(policy, pre, post, case, noise, torch.float32)
        rec_l = infer(loaded, pre_l, post_l, case, noise, torch.float32)
        for key in ("tokens", "state_norm", "prefix_embs", "actions_norm", "actions"):
            assert torch.equal(rec[key], rec_l[key]), f"{name}.{key}: reloaded checkpoint differs"
        rec64 = f64_pass(loaded, pre_l, post_l, case, noise)
        assert torch.equal(rec64["tokens"], rec_l["tokens"]), f"{name}: float64 tokens differ (a state bin edge)"
        t, d = flatten(name, case, rec_l, noise)
        t64, _ = flatten(name, case, rec64, noise)
        for key, v in t.items():
            if v.dtype == torch.float32 and ".raw." not in key and not key.endswith(".noise"):
                v64 = t64[key]
                assert v64.dtype == torch.float64, key
                diff = (v.double() - v64).abs()
                if ".layer." in key:
                    diff = diff[t[f"{name}.prefix_pad_mask"].bool()[:, :, None, None].expand_as(v)]
                errors[key] = {"max_abs": diff.max().item(), "max_abs_value": v64.abs().max().item()}
                if ".image." not in key:  # images have no stored twin (fixture size); their error is in meta
                    tensors[f"{key}.f64"] = v64.contiguous()
                    d[f"{key}.f64"] = {"shape": list(v64.shape), "dtype": "float64", "layout": f"as {key}, float64"}
        tensors.update(t)
        described.update(d)
        case_meta[name] = {
            "batch": len(case["tasks"]),
            "tasks": case["tasks"],
            "prompts": rec_l["prompts"],
            "raw_cameras": {k: list(v.shape[1:3]) for k, v in case["images"].items()},
            "image_slots": len(rec_l["images"]),
            "prefix_len": rec_l["prefix_embs"].shape[1],
            "prefix_valid": rec_l["prefix_pad_mask"].sum(1).tolist(),
            "pngs": write_pngs(out / "golden", name, case),
        }

    import lerobot
    import tokenizers
    import transformers

    save_file(tensors, str(out / "golden/goldens.safetensors"), metadata={"lerobot": lerobot.__version__})
    vlm = TINY_GEMMA["gemma_2b"]
    meta = {
        "generator": "engine/tools/pi_fixture.py",
        "family": family,
        "versions": {"lerobot": lerobot.__version__, "torch": torch.__version__,
                     "transformers": transformers.__version__, "tokenizers": tokenizers.__version__},
        "seed": SEED,
        "tokenizer": {"file": "tokenizer.json", "pad_id": tokenizer.pad_token_id, "bos_id": tokenizer.bos_token_id,
                      "vocab": tokenizer.vocab_size, "max_length": FAMILIES[family][1],
                      "padding": "max_length", "padding_side": "right"},
        "rename_map": RENAME,
        "dims": {"state": STATE_DIM, "action": ACTION_DIM, "chunk": CHUNK, "max_state_dim": 32,
                 "max_action_dim": 32, "num_steps": 10, "image_size": IMAGE,
                 "patch_size": TINY_SIGLIP["patch_size"], "tokens_per_camera": (IMAGE // TINY_SIGLIP["patch_size"]) ** 2,
                 "vision": TINY_SIGLIP, "vlm": vlm, "expert": TINY_GEMMA["gemma_300m"], "vocab": VOCAB},
        "cases": case_meta,
        "tensors": described,
        "lerobot_f32_vs_f64": errors,
    }
    (out / "golden/meta.json").write_text(json.dumps(meta, indent=1) + "\n")
    total = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    for name, e in errors.items():
        print(f"{name:40s} |f32-f64| {e['max_abs']:.2e}  (max |x| {e['max_abs_value']:.2e})")
    print(f"wrote {out} ({total / 1e6:.2f} MB): {sorted(p.name for p in out.iterdir())}")
    assert total < 5e6, f"{out} is {total / 1e6:.2f} MB"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", choices=sorted(FAMILIES), help="write one fixture")
    ap.add_argument("--out-dir", type=Path, default=REPO / "engine/tests/fixtures")
    args = ap.parse_args()
    torch.set_num_threads(2)
    for family in FAMILIES:
        if args.only in (None, family):
            write_fixture(family, args.out_dir / f"{family}_tiny")


if __name__ == "__main__":
    main()
