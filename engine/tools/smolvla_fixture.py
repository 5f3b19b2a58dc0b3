#!/usr/bin/env python3
"""Regenerate `engine/tests/fixtures/smolvla_tiny/`: a small random SmolVLA checkpoint as LeRobot
0.6.1 saves it, plus golden intermediates of LeRobot's own inference on it.

    python3 engine/tools/smolvla_fixture.py            # writes engine/tests/fixtures/smolvla_tiny/

The checkpoint directory is what a user's fine-tuned SmolVLA looks like, at toy size:

- `config.json`, `model.safetensors`: `SmolVLAPolicy.save_pretrained` (VLM and expert, float32).
- `policy_preprocessor.json`, `policy_postprocessor.json` and the normaliser stats files they
  name through `state_file`: `make_smolvla_pre_post_processors(...)[i].save_pretrained`.
  The preprocessor's rename map sends `observation.images.top` to `observation.images.camera1`.
  State is MEAN_STD, action QUANTILES, images IDENTITY (camera1 has stats anyway, unused).
- `tokenizer.json`: a byte-level BPE (SmolLM2's pre-tokenizer: single digits, then GPT-2 byte
  level) trained with the `tokenizers` library on a fixed corpus; 320 tokens, `<|im_end|>`
  (id 2) pads. It stands in for SmolVLM2's tokenizer, which LeRobot fetches from the hub.
- `vlm_config.json`: the SmolVLM config the VLM was built from (LeRobot fetches it from the hub
  by `vlm_model_name`; this one is not on the hub).

`golden/` holds the cases, run through LeRobot's real inference path (`prepare_observation_for_
inference`-style u8 -> [0,1], the preprocessor pipeline, `predict_action_chunk` with fixed
noise, the postprocessor), with the intermediates recorded by wrapping LeRobot's own functions
(`prepare_images`, `embed_image`, the vision model, `embed_prefix`, the prefix pass of
`vlm_with_expert.forward`, `denoise_step`): nothing is re-implemented. `golden/meta.json`
describes every tensor of `golden/goldens.safetensors`. Every float tensor `X` also has `X.f64`:
the same LeRobot code run in float64 (weights and inputs in double, and LeRobot's explicit
float32 casts redirected to float64, see `smolvla_common.float64_casts`), so a test can bound
LeRobot's own float32 rounding (`meta.json` -> `lerobot_f32_vs_f64`).

Cases (`golden/meta.json` -> `cases`):
- `pair`: 2 observations; camera1 (sent as `top`, renamed) 37x53 and camera2 131x61 u8 images
  (one upscaled, one downscaled into 96x96 with left/top padding); the first task is long enough
  to be truncated at the tokenizer's 16 tokens, the second is short (padded to 16); non-zero
  states. The config's `empty_cameras: 1` adds a masked all -1 camera.
- `missing`: 1 observation without camera2: LeRobot fills it with the empty camera (one slot,
  masked), so the prefix has 2 camera blocks instead of 3; the task is short (no padding, since
  padding is to the longest in the batch).

The checkpoint is reloaded from disk with LeRobot's own `from_pretrained` (policy and both
processors) and re-run: the goldens are asserted bit-identical, so the files are exactly what
LeRobot loads. Seeded: rerunning writes the same tensors (on the same torch build).
"""

import argparse
import copy
import json
import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from lerobot_env import REPO, ensure_venv  # noqa: E402

ensure_venv()

import numpy as np  # noqa: E402
import torch  # noqa: E402
from safetensors.torch import save_file  # noqa: E402

from smolvla_common import BF16_PREFIX, feature_stats, float64_casts, patch_hub, rescale_weights, store_vlm_in_bf16  # noqa: E402

SEED = 20261125
TEXT_CONFIG = dict(
    model_type="llama",
    hidden_size=96,
    intermediate_size=128,
    num_hidden_layers=6,  # the checkpoint keeps num_vlm_layers = 4 of them, as smolvla_base keeps 16 of 32
    num_attention_heads=6,
    num_key_value_heads=2,
    head_dim=16,
    rms_norm_eps=1e-5,
    vocab_size=320,
    max_position_embeddings=256,
    rope_theta=100000.0,  # LeRobot ignores it (its own RoPE uses wavelength 10 000): a trap on purpose
    pad_token_id=2,
    tie_word_embeddings=False,
)
VISION_CONFIG = dict(
    hidden_size=32,
    intermediate_size=64,
    num_hidden_layers=2,
    num_attention_heads=2,
    image_size=96,
    patch_size=8,  # 12 x 12 patches
    num_channels=3,
    layer_norm_eps=1e-6,
    hidden_act="gelu_pytorch_tanh",
)
SCALE_FACTOR = 4  # pixel shuffle 12 x 12 -> 3 x 3 = 9 tokens per camera, as SmolVLM2 (32 x 32 -> 64)
NUM_VLM_LAYERS = 4
CHUNK = 16
STATE_DIM = 7
ACTION_DIM = 6
TOKENIZER_MAX = 16
VOCAB = 320
SPECIAL_TOKENS = ["<|endoftext|>", "<|im_start|>", "<|im_end|>"]
PAD_TOKEN = "<|im_end|>"
CAMERAS = ("observation.images.camera1", "observation.images.camera2")
RENAME = {"observation.images.top": "observation.images.camera1"}
CORPUS = [
    "pick up the cube",
    "pick up the red cube and place it in the bin",
    "put the blue block on the plate",
    "open the drawer and take out the sponge",
    "move the arm to the home position",
    "stack 3 green cups on top of each other",
    "push the 2 yellow balls to the left side of the table",
    "grasp the handle, turn it 90 degrees and release",
    "place the bottle next to the cube",
    "wipe the table with the cloth",
]
LONG_TASK = (
    "pick up the red cube from the left bin, rotate it 180 degrees and place it gently "
    "on the blue plate next to 3 green cups"
)
SHORT_TASK = "pick up the cube"
MISSING_TASK = "put the blue block on the plate"


def train_tokenizer(path: Path):
    """A byte-level BPE with SmolLM2's pre-tokenizer, trained on CORPUS; saved as tokenizer.json."""
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers, trainers

    tok = Tokenizer(models.BPE())
    tok.pre_tokenizer = pre_tokenizers.Sequence(
        [pre_tokenizers.Digits(individual_digits=True), pre_tokenizers.ByteLevel(add_prefix_space=False)]
    )
    tok.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(
        vocab_size=VOCAB,
        special_tokens=SPECIAL_TOKENS,
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
        show_progress=False,
    )
    tok.train_from_iterator(CORPUS * 4, trainer)
    assert tok.get_vocab_size() <= TEXT_CONFIG["vocab_size"], tok.get_vocab_size()
    tok.save(str(path))
    return tok


def hf_tokenizer(path: Path):
    from transformers import PreTrainedTokenizerFast

    return PreTrainedTokenizerFast(
        tokenizer_file=str(path), pad_token=PAD_TOKEN, eos_token=PAD_TOKEN, bos_token="<|im_start|>"
    )


def build(tokenizer):
    from transformers import SmolVLMConfig

    from lerobot.configs.types import FeatureType, NormalizationMode, PolicyFeature
    from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
    from lerobot.policies.smolvla.processor_smolvla import make_smolvla_pre_post_processors

    vlm_config = SmolVLMConfig(
        text_config=dict(TEXT_CONFIG), vision_config=dict(VISION_CONFIG), scale_factor=SCALE_FACTOR
    )
    patch_hub(vlm_config, tokenizer)
    size = VISION_CONFIG["image_size"]
    cfg = SmolVLAConfig(
        chunk_size=CHUNK,
        n_action_steps=CHUNK,
        num_steps=10,
        max_state_dim=32,
        max_action_dim=32,
        resize_imgs_with_padding=(size, size),
        empty_cameras=1,
        tokenizer_max_length=TOKENIZER_MAX,
        num_vlm_layers=NUM_VLM_LAYERS,
        self_attn_every_n_layers=2,
        expert_width_multiplier=0.75,
        attention_mode="cross_attn",
        load_vlm_weights=False,
        device="cpu",
        normalization_mapping={
            "VISUAL": NormalizationMode.IDENTITY,
            "STATE": NormalizationMode.MEAN_STD,
            "ACTION": NormalizationMode.QUANTILES,
        },
        input_features={
            "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(STATE_DIM,)),
            CAMERAS[0]: PolicyFeature(type=FeatureType.VISUAL, shape=(3, 37, 53)),
            CAMERAS[1]: PolicyFeature(type=FeatureType.VISUAL, shape=(3, 131, 61)),
        },
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(ACTION_DIM,))},
    )
    torch.manual_seed(SEED)
    policy = SmolVLAPolicy(cfg).eval()
    rescale_weights(policy, SEED)
    with torch.no_grad():  # bf16-representable VLM weights: the file stores them in bf16 (see BF16_PREFIX)
        for name, p in policy.named_parameters():
            if name.startswith(BF16_PREFIX):
                p.copy_(p.to(torch.bfloat16).float())

    gen = torch.Generator().manual_seed(SEED + 7)

    stats = {
        "observation.state": feature_stats(gen, STATE_DIM, 2.0),
        "action": feature_stats(gen, ACTION_DIM, 1.5),
        # Real checkpoints carry image stats too; IDENTITY leaves them unused.
        CAMERAS[0]: {
            "mean": torch.rand(3, 1, 1, generator=gen),
            "std": 0.2 + torch.rand(3, 1, 1, generator=gen),
            "min": torch.zeros(3, 1, 1),
            "max": torch.ones(3, 1, 1),
        },
    }
    pre, post = make_smolvla_pre_post_processors(cfg, dataset_stats=stats)
    pre.steps[0].rename_map = dict(RENAME)
    return policy, pre, post, vlm_config


def make_cases():
    """Raw observations as a robot gives them: u8 HWC images, f32 state, task text."""
    gen = torch.Generator().manual_seed(SEED + 1)

    def image(h, w):
        # Smooth gradients plus noise: resizing has something to interpolate.
        yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
        base = torch.stack([xx * 255 / max(w - 1, 1), yy * 255 / max(h - 1, 1), (xx + yy) * 127 / (h + w)], -1)
        noisy = base + 40 * torch.randn(h, w, 3, generator=gen)
        return noisy.clamp(0, 255).round().to(torch.uint8)

    pair = {
        "tasks": [LONG_TASK, SHORT_TASK],
        "images": {
            "observation.images.top": torch.stack([image(37, 53), image(37, 53)]),
            CAMERAS[1]: torch.stack([image(131, 61), image(131, 61)]),
        },
        "state": 1.5 * torch.randn(2, STATE_DIM, generator=gen),
    }
    missing = {
        "tasks": [MISSING_TASK],
        "images": {"observation.images.top": image(37, 53)[None]},
        "state": 1.5 * torch.randn(1, STATE_DIM, generator=gen),
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

    def __init__(self, policy):
        self.policy = policy
        self.rec = {}
        model = policy.model
        vwe = model.vlm_with_expert
        self.saved = [
            (policy, "prepare_images", policy.prepare_images),
            (policy, "prepare_state", policy.prepare_state),
            (vwe, "embed_image", vwe.embed_image),
            (model, "embed_prefix", model.embed_prefix),
            (vwe, "forward", vwe.forward),
            (model, "denoise_step", model.denoise_step),
        ]
        rec = self.rec

        def prepare_images(batch):
            images, masks = self.saved[0][2](batch)
            rec["images"] = [i.clone() for i in images]
            rec["image_masks"] = [m.clone() for m in masks]
            return images, masks

        def prepare_state(batch):
            state = self.saved[1][2](batch)
            rec["state_padded"] = state.clone()
            return state

        def embed_image(image):
            out = self.saved[2][2](image)
            rec.setdefault("connector", []).append(out.clone())
            return out

        def embed_prefix(*a, **k):
            embs, pad, att = self.saved[3][2](*a, **k)
            rec["prefix_embs"] = embs.clone()
            rec["prefix_pad_mask"] = pad.clone()
            rec["prefix_att_mask"] = att.clone()
            return embs, pad, att

        def forward(**kw):
            out, cache = self.saved[4][2](**kw)
            if kw["inputs_embeds"][1] is None:  # the prefix pass, which fills the KV cache
                rec["prefix_positions"] = kw["position_ids"].clone()
                rec["prefix_att_2d"] = kw["attention_mask"].clone()
                # DynamicCache holds [batch, kv_heads, seq, head_dim]; store [batch, seq, kv_heads, head_dim].
                rec["keys"] = [layer.keys.transpose(1, 2).clone() for layer in cache.layers]
                rec["values"] = [layer.values.transpose(1, 2).clone() for layer in cache.layers]
            return out, cache

        def denoise_step(**kw):
            v = self.saved[5][2](**kw)
            rec.setdefault("velocities", []).append(v.clone())
            return v

        policy.prepare_images = prepare_images
        policy.prepare_state = prepare_state
        vwe.embed_image = embed_image
        model.embed_prefix = embed_prefix
        vwe.forward = forward
        model.denoise_step = denoise_step
        vision = vwe.get_vlm_model().vision_model
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
    rec = Recorder(policy)
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
    put("tokens", rec["tokens"], "[batch, len] i64; len = longest task in the batch, at most tokenizer max_length")
    put("token_mask", rec["token_mask"], "[batch, len] u8, 1 = real token")
    put("state_norm", rec["state_norm"], "[batch, state_dim] f32, after the preprocessor's normaliser")
    put("state_padded", rec["state_padded"], "[batch, max_state_dim] f32, state_norm zero-padded (prepare_state)")
    for i, (img, m) in enumerate(zip(rec["images"], rec["image_masks"], strict=True)):
        put(f"image.{i}", img, "[batch, 3, H, W] f32 in [-1,1]: resize_with_pad (left/top) then x*2-1; "
            "slot i in LeRobot's order (present cameras in config order, then empty cameras)")
        put(f"image_mask.{i}", m, "[batch] u8, 0 = missing camera (all -1 image)")
    for i, v in enumerate(rec["vision"]):
        put(f"vision.{i}", v, "[batch, patches, vision_hidden] f32, SigLIP last_hidden_state (after post_layernorm)")
    for i, c in enumerate(rec["connector"]):
        put(f"connector.{i}", c, "[batch, tokens, text_hidden] f32, pixel shuffle + modality projection "
            "(before embed_prefix's x sqrt(hidden))")
    put("prefix_embs", rec["prefix_embs"], "[batch, prefix_len, text_hidden] f32: per camera slot connector "
        "x sqrt(hidden), then language embeddings x sqrt(hidden), then state_proj(state_padded)")
    put("prefix_pad_mask", rec["prefix_pad_mask"], "[batch, prefix_len] u8, 1 = valid token")
    put("prefix_att_mask", rec["prefix_att_mask"], "[batch, prefix_len] u8, LeRobot's att_masks (1 = new causal block: the state token)")
    put("prefix_positions", rec["prefix_positions"], "[batch, prefix_len] i64, cumsum(pad_mask) - 1")
    for i, (k, v) in enumerate(zip(rec["keys"], rec["values"], strict=True)):
        note = "compare only where prefix_pad_mask is 1: padded positions hold LeRobot's values for pad tokens"
        put(f"layer.{i}.key", k, "[batch, prefix_len, kv_heads, head_dim] f32, post-RoPE (the PrefixKv layout)", note)
        put(f"layer.{i}.value", v, "[batch, prefix_len, kv_heads, head_dim] f32", note)
    put("velocities", torch.stack(rec["velocities"]), "[steps, batch, chunk, max_action_dim] f32, each denoise_step's v")
    put("actions_norm", rec["actions_norm"], "[batch, chunk, action_dim] f32, predict_action_chunk's output (normalised)")
    put("actions", rec["actions"], "[batch, chunk, action_dim] f32, after the postprocessor (unnormalised)")
    return out, desc


def f64_pass(policy, pre, post, case, noise):
    """The same LeRobot inference in float64 (see float64_casts)."""
    import lerobot.policies.common.vla_utils as vla_utils
    import lerobot.policies.smolvla.modeling_smolvla as ms
    import lerobot.policies.smolvla.smolvlm_with_expert as swe
    import transformers.models.llama.modeling_llama as llama

    policy64 = copy.deepcopy(policy).double()
    pre64, post64 = copy.deepcopy(pre), copy.deepcopy(post)
    with float64_casts(swe, ms, vla_utils, llama):
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


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=REPO / "engine/tests/fixtures/smolvla_tiny")
    args = ap.parse_args()
    out = args.out
    if out.exists():
        shutil.rmtree(out)
    (out / "golden").mkdir(parents=True)
    torch.set_num_threads(2)

    train_tokenizer(out / "tokenizer.json")
    tokenizer = hf_tokenizer(out / "tokenizer.json")
    policy, pre, post, vlm_config = build(tokenizer)
    policy.save_pretrained(out)
    store_vlm_in_bf16(out / "model.safetensors")
    pre.save_pretrained(out)
    post.save_pretrained(out)
    (out / "vlm_config.json").write_text(vlm_config.to_json_string())

    # Reload everything from disk with LeRobot's own loaders: the goldens come from these files.
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
    from lerobot.processor import PolicyProcessorPipeline
    from lerobot.processor.converters import policy_action_to_transition, transition_to_policy_action

    loaded = SmolVLAPolicy.from_pretrained(out).eval()
    pre_l = PolicyProcessorPipeline.from_pretrained(out, config_filename="policy_preprocessor.json")
    post_l = PolicyProcessorPipeline.from_pretrained(
        out,
        config_filename="policy_postprocessor.json",
        to_transition=policy_action_to_transition,
        to_output=transition_to_policy_action,
    )

    cases, noises = make_cases()
    tensors, described, errors, case_meta = {}, {}, {}, {}
    for name, case in cases.items():
        noise = noises[name]
        rec = infer(policy, pre, post, case, noise, torch.float32)
        rec_l = infer(loaded, pre_l, post_l, case, noise, torch.float32)
        for key in ("tokens", "state_norm", "prefix_embs", "actions_norm", "actions"):
            assert torch.equal(rec[key], rec_l[key]), f"{name}.{key}: reloaded checkpoint differs"
        t, d = flatten(name, case, rec_l, noise)
        t64, _ = flatten(name, case, f64_pass(loaded, pre_l, post_l, case, noise), noise)
        for key, v in t.items():
            if v.dtype == torch.float32 and ".raw." not in key and not key.endswith(".noise"):
                # Images and velocities have no stored f64 twin (fixture size); their error is in meta.
                keep64 = ".image." not in key and not key.endswith(".velocities")
                v64 = t64[key]
                assert v64.dtype == torch.float64, key
                mask = None
                if ".layer." in key:
                    mask = t[f"{name}.prefix_pad_mask"].bool()[:, :, None, None].expand_as(v)
                diff = (v.double() - v64).abs()
                if mask is not None:
                    diff = diff[mask]
                errors[key] = {
                    "max_abs": diff.max().item(),
                    "max_abs_value": v64.abs().max().item(),
                }
                if keep64:
                    tensors[f"{key}.f64"] = v64.contiguous()
                    d[f"{key}.f64"] = {"shape": list(v64.shape), "dtype": "float64", "layout": f"as {key}, float64"}
        tensors.update(t)
        described.update(d)
        case_meta[name] = {
            "batch": len(case["tasks"]),
            "tasks": case["tasks"],
            "raw_cameras": {k: list(v.shape[1:3]) for k, v in case["images"].items()},
            "image_slots": len(rec_l["images"]),
            "prefix_len": rec_l["prefix_embs"].shape[1],
            "prefix_valid": rec_l["prefix_pad_mask"].sum(1).tolist(),
            "token_len": rec_l["tokens"].shape[1],
            "pngs": write_pngs(out / "golden", name, case),
        }

    import lerobot
    import tokenizers
    import transformers

    save_file(tensors, str(out / "golden/goldens.safetensors"), metadata={"lerobot": lerobot.__version__})
    vision_attn = loaded.model.vlm_with_expert.get_vlm_model().vision_model.config._attn_implementation
    meta = {
        "generator": "engine/tools/smolvla_fixture.py",
        "versions": {"lerobot": lerobot.__version__, "torch": torch.__version__,
                     "transformers": transformers.__version__, "tokenizers": tokenizers.__version__},
        "seed": SEED,
        "vision_attention": vision_attn,
        "tokenizer": {"file": "tokenizer.json", "pad_token": PAD_TOKEN,
                      "pad_id": tokenizer.pad_token_id, "vocab": tokenizer.vocab_size,
                      "max_length": TOKENIZER_MAX, "padding": "longest", "padding_side": "right"},
        "rename_map": RENAME,
        "dims": {"state": STATE_DIM, "action": ACTION_DIM, "chunk": CHUNK, "max_state_dim": 32,
                 "max_action_dim": 32, "num_steps": 10, "image_size": VISION_CONFIG["image_size"],
                 "patch_size": VISION_CONFIG["patch_size"], "scale_factor": SCALE_FACTOR,
                 "tokens_per_camera": (VISION_CONFIG["image_size"] // VISION_CONFIG["patch_size"]) ** 2
                 // SCALE_FACTOR**2, "num_vlm_layers": NUM_VLM_LAYERS,
                 "text_hidden": TEXT_CONFIG["hidden_size"], "vision_hidden": VISION_CONFIG["hidden_size"],
                 "kv_heads": TEXT_CONFIG["num_key_value_heads"], "head_dim": TEXT_CONFIG["head_dim"]},
        "cases": case_meta,
        "tensors": described,
        "lerobot_f32_vs_f64": errors,
    }
    (out / "golden/meta.json").write_text(json.dumps(meta, indent=1) + "\n")
    total = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    for name, e in errors.items():
        print(f"{name:40s} |f32-f64| {e['max_abs']:.2e}  (max |x| {e['max_abs_value']:.2e})")
    print(f"wrote {out} ({total / 1e6:.2f} MB): {sorted(p.name for p in out.iterdir())}")


if __name__ == "__main__":
    main()
