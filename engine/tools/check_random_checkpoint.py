#!/usr/bin/env python3
"""Check that LeRobot 0.6.1 loads a random SmolVLA checkpoint folder written by
`kairos-tiny-model --preset smolvla-base` (`kairos_engine::smolvla::random_checkpoint`).

    cargo run -p kairos-tests --bin kairos-tiny-model -- --preset smolvla-base DIR
    python3 engine/tools/check_random_checkpoint.py DIR

LeRobot's own loaders read the folder: `SmolVLAPolicy.from_pretrained` (the VLM built from the
folder's `vlm_config.json` instead of the hub's, as `smolvla_fixture.py` does) and both
`PolicyProcessorPipeline.from_pretrained`. Every tensor of `model.safetensors` must be a
parameter of the loaded policy with that exact value, and every parameter must come from the
file; the processors must have read their stats files. Exits non-zero otherwise. Not run in CI.
"""
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from lerobot_env import ensure_venv  # noqa: E402

ensure_venv()

import torch  # noqa: E402
from safetensors.torch import load_file  # noqa: E402

from smolvla_common import patch_hub  # noqa: E402


def main() -> int:
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    folder = Path(sys.argv[1])
    from transformers import PreTrainedTokenizerFast, SmolVLMConfig

    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
    from lerobot.processor import PolicyProcessorPipeline

    vlm = json.loads((folder / "vlm_config.json").read_text())
    vlm_config = SmolVLMConfig(
        text_config=vlm["text_config"], vision_config=vlm["vision_config"], scale_factor=vlm["scale_factor"]
    )
    tokenizer = PreTrainedTokenizerFast(tokenizer_file=str(folder / "tokenizer.json"))
    patch_hub(vlm_config, tokenizer)

    policy = SmolVLAPolicy.from_pretrained(folder).eval()
    pre = PolicyProcessorPipeline.from_pretrained(folder, config_filename="policy_preprocessor.json")
    post = PolicyProcessorPipeline.from_pretrained(folder, config_filename="policy_postprocessor.json")

    stored = load_file(str(folder / "model.safetensors"))
    params = policy.state_dict()
    problems = []
    for name, t in stored.items():
        p = params.get(name)
        if p is None:
            problems.append(f"{name}: in the file, not a parameter of the policy")
        elif p.shape != t.shape:
            problems.append(f"{name}: file {tuple(t.shape)}, policy {tuple(p.shape)}")
        elif not torch.equal(p.to(t.dtype), t):
            problems.append(f"{name}: the policy's value is not the file's")
    # Buffers LeRobot derives at construction (not saved) are not expected in the file.
    unsaved = [n for n in params if n not in stored and "rotary" not in n and "inv_freq" not in n]
    problems += [f"{n}: a parameter of the policy, missing from the file" for n in unsaved]
    steps = [type(s).__name__ for s in pre.steps] + [type(s).__name__ for s in post.steps]
    count = sum(t.numel() for t in stored.values())
    dtypes = sorted({str(t.dtype) for t in stored.values()})
    print(f"{folder}: {len(stored)} tensors, {count / 1e6:.1f} M values, dtypes {dtypes}")
    print(f"processors: {steps}")
    for p in problems[:20]:
        print("MISMATCH", p)
    print("LeRobot loads it: OK" if not problems else f"{len(problems)} problems")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
