"""What the engine's π0 / π0.5 tools share: a PaliGemma-style tokenizer written offline, LeRobot's
π policies built without the hub (at full size or toy size). Random dataset statistics are
`smolvla_common.feature_stats`, which the SmolVLA fixture shares.

LeRobot hard-codes the π architecture: `get_gemma_config` knows only `gemma_2b` and
`gemma_300m`, and `PaliGemmaWithExpertModel` builds SigLIP so400m/14 and a 257 152-token
vocabulary. At full size only the tokenizer's hub look-up (`google/paligemma-3b-pt-224`) is
replaced. A toy model (`ToySizes`) replaces exactly those three size choices and nothing else;
every module's code runs unchanged. Import this module only after `lerobot_env.ensure_venv()`.
"""

import json
from dataclasses import dataclass, field
from pathlib import Path

import torch

# google/paligemma-3b-pt-224's vocabulary: Gemma's 256 000 tokens, 1 024 `<locNNNN>` and 128
# `<segNNN>` tokens; LeRobot's π models always build their embeddings with this many rows.
PALIGEMMA_VOCAB = 257152
SPECIAL = ["<pad>", "<eos>", "<bos>", "<unk>"]
# The trained part of the tokenizer: enough merges that prompts become words, not bytes.
CORPUS = [
    "pick up the cube",
    "pick up the red cube and place it in the bin",
    "put the blue block on the plate",
    "open the drawer and take out the sponge",
    "move the arm to the home position",
    "stack 3 green cups on top of each other",
    "Task: fold the towel, State: 12 128 255 0 64 200 31;\nAction: ",
    "Task: grasp the handle, State: 7 99 143 250 1 18 77;\nAction: ",
    "wipe the table with the cloth",
]
TRAINED_VOCAB = 384


@dataclass(frozen=True)
class ToySizes:
    """The sizes a toy π model gets in place of LeRobot's hard-coded ones."""

    gemma: dict = field(
        default_factory=lambda: {
            # 8 query heads and 1 KV head as in gemma_2b / gemma_300m (8 is also hard-coded in
            # LeRobot's joint forward); the VLM's width differs from heads x head_dim (as the
            # expert's does at full size), the two share head_dim.
            "gemma_2b": dict(width=64, depth=3, mlp_dim=128, num_heads=8, num_kv_heads=1, head_dim=8),
            "gemma_300m": dict(width=32, depth=3, mlp_dim=64, num_heads=8, num_kv_heads=1, head_dim=8),
        }
    )
    # SigLIP so400m/14 keeps its patch 14 and 16 heads; width 64 (head dim 4), 2 layers.
    siglip: dict = field(
        default_factory=lambda: dict(
            hidden_size=64, intermediate_size=128, num_hidden_layers=2, num_attention_heads=16, patch_size=14
        )
    )
    vocab: int = TRAINED_VOCAB


def write_tokenizer(path: Path, vocab: int = TRAINED_VOCAB):
    """A Gemma-style BPE trained on CORPUS, saved as `path` (+ tokenizer_config.json beside it).

    Spaces as `▁`, byte fallback, `<bos>` prepended by the post-processor, `<pad>` id 0. With
    `vocab` above what training yields, the BPE vocabulary is filled up to `vocab` ids with
    `<unusedN>` tokens: no merge produces them, so the tokenization is the trained one, but the
    tokenizer's size (and so the embedding table a model needs for it) is `vocab`.
    """
    from tokenizers import Tokenizer, decoders, models, normalizers, processors, trainers

    tok = Tokenizer(models.BPE(unk_token="<unk>", byte_fallback=True))
    tok.normalizer = normalizers.Replace(" ", "▁")
    tok.decoder = decoders.Sequence([decoders.Replace("▁", " "), decoders.ByteFallback(), decoders.Fuse()])
    bytes_ = [f"<0x{b:02X}>" for b in range(256)]
    trainer = trainers.BpeTrainer(vocab_size=TRAINED_VOCAB, special_tokens=SPECIAL + bytes_, show_progress=False)
    tok.train_from_iterator(CORPUS * 4, trainer)
    tok.post_processor = processors.TemplateProcessing(single="<bos> $A", special_tokens=[("<bos>", 2)])
    trained = tok.get_vocab_size()
    assert trained <= min(vocab, TRAINED_VOCAB), trained
    assert [tok.token_to_id(t) for t in SPECIAL] == [0, 1, 2, 3]
    tok.save(str(path))
    if vocab > trained:
        spec = json.loads(path.read_text())
        table = spec["model"]["vocab"]
        assert sorted(table.values()) == list(range(trained))
        table.update({f"<unused{i - trained}>": i for i in range(trained, vocab)})
        path.write_text(json.dumps(spec, ensure_ascii=False))
        assert Tokenizer.from_file(str(path)).get_vocab_size() == vocab
    (path.parent / "tokenizer_config.json").write_text(
        json.dumps(
            {"bos_token": "<bos>", "eos_token": "<eos>", "pad_token": "<pad>", "unk_token": "<unk>",
             "add_bos_token": True, "add_eos_token": False, "tokenizer_class": "GemmaTokenizer"},
            indent=2,
        )
        + "\n"
    )


def hf_tokenizer(path: Path):
    """The tokenizer file as LeRobot's tokenizer step uses it (a transformers fast tokenizer)."""
    from transformers import PreTrainedTokenizerFast

    return PreTrainedTokenizerFast(
        tokenizer_file=str(path), pad_token="<pad>", eos_token="<eos>", bos_token="<bos>", unk_token="<unk>"
    )


def patch_lerobot(tokenizer, toy: ToySizes | None = None):
    """LeRobot's tokenizer step gets `tokenizer`; with `toy`, its π models get toy sizes."""
    import lerobot.policies.pi0.modeling_pi0 as m0
    import lerobot.policies.pi05.modeling_pi05 as m05
    import lerobot.processor.tokenizer_processor as tp

    tp.AutoTokenizer.from_pretrained = staticmethod(lambda *_a, **_k: tokenizer)
    if toy is None:
        return
    for m in (m0, m05):
        if getattr(m, "_kairos_patched", False):
            continue
        real_pali = m.PaliGemmaForConditionalGenerationWithPiGemma
        real_expert = m.PiGemmaForCausalLM
        gemma_config = m.GemmaConfig

        def get_gemma_config(variant, _cfg=gemma_config):
            return _cfg(**toy.gemma[variant])

        def paligemma(config, _real=real_pali):
            for k, v in toy.siglip.items():
                setattr(config.vision_config, k, v)
            config.vision_config.projection_dim = config.text_config.hidden_size
            config.text_config.vocab_size = toy.vocab
            return _real(config=config)

        def expert(config, _real=real_expert):
            config.vocab_size = toy.vocab
            return _real(config=config)

        m.get_gemma_config = get_gemma_config
        m.PaliGemmaForConditionalGenerationWithPiGemma = paligemma
        m.PiGemmaForCausalLM = expert
        m._kairos_patched = True


def policy_classes(family):
    """LeRobot's (config class, policy class, processor factory) for `pi0` or `pi05`."""
    if family == "pi0":
        from lerobot.policies.pi0.configuration_pi0 import PI0Config as Config
        from lerobot.policies.pi0.modeling_pi0 import PI0Policy as Policy
        from lerobot.policies.pi0.processor_pi0 import make_pi0_pre_post_processors as make_processors
    elif family == "pi05":
        from lerobot.policies.pi05.configuration_pi05 import PI05Config as Config
        from lerobot.policies.pi05.modeling_pi05 import PI05Policy as Policy
        from lerobot.policies.pi05.processor_pi05 import make_pi05_pre_post_processors as make_processors
    else:
        raise ValueError(f"unknown π family {family!r}")
    return Config, Policy, make_processors
