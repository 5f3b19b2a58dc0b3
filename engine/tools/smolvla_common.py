"""What the engine's LeRobot tools share: building a SmolVLA offline, giving it usable weights, and
random dataset statistics (`feature_stats`, for the SmolVLA and π fixtures and benchmarks).

LeRobot's `SmolVLMWithExpertModel` asks the hub for the VLM's config (`AutoConfig`) and processor
(`AutoProcessor`), and its tokenizer step asks for the tokenizer (`AutoTokenizer`). None of the
tools may reach the hub: `patch_hub` hands LeRobot local objects instead; LeRobot's code itself
runs unchanged. Import this module only after `lerobot_env.ensure_venv()`.
"""

import types

import torch

# HuggingFaceTB/SmolVLM2-500M-Video-Instruct, as lerobot/smolvla_base uses it.
SMOLVLM2_500M_TEXT = dict(
    model_type="llama",
    hidden_size=960,
    intermediate_size=2560,
    num_hidden_layers=32,
    num_attention_heads=15,
    num_key_value_heads=5,
    head_dim=64,
    rms_norm_eps=1e-5,
    vocab_size=49280,
    max_position_embeddings=8192,
    rope_theta=100000.0,
    tie_word_embeddings=False,
)
SMOLVLM2_500M_VISION = dict(
    hidden_size=768,
    intermediate_size=3072,
    num_hidden_layers=12,
    num_attention_heads=12,
    image_size=512,
    patch_size=16,
    num_channels=3,
    layer_norm_eps=1e-6,
    hidden_act="gelu_pytorch_tanh",
)
SMOLVLM2_500M_SCALE_FACTOR = 4
# As in lerobot/smolvla_base's model.safetensors, the VLM's tensors are stored in bf16 and the
# expert's in f32; LeRobot loads both into its float32 modules.
BF16_PREFIX = "model.vlm_with_expert.vlm."


def patch_hub(vlm_config, tokenizer=None):
    """Make LeRobot build its VLM from `vlm_config` (and tokenize with `tokenizer`) without the hub."""
    import lerobot.policies.smolvla.smolvlm_with_expert as swe
    import lerobot.processor.tokenizer_processor as tp

    class _Tokenizer:  # only these two ids are read, and only with add_image_special_tokens
        fake_image_token_id = 1
        global_image_token_id = 2

    class _Processor:
        tokenizer = _Tokenizer()

    swe.AutoConfig.from_pretrained = staticmethod(lambda *_a, **_k: vlm_config)
    swe.AutoProcessor.from_pretrained = staticmethod(lambda *_a, **_k: _Processor())
    if tokenizer is not None:
        tp.AutoTokenizer.from_pretrained = staticmethod(lambda *_a, **_k: tokenizer)


@torch.no_grad()
def rescale_weights(module, seed, progress=None):
    """HF init (std 0.02) makes every activation tiny; use unit-gain weights so attention and SiLU matter.

    `progress(fraction)`, if given, is called after each parameter with the fraction done.
    """
    gen = torch.Generator().manual_seed(seed)
    named = list(module.named_parameters())
    total, done = sum(p.numel() for _, p in named), 0
    for name, p in named:
        if p.ndim >= 2:
            fan_in = p.shape[1] if p.ndim == 2 else p[0].numel()
            p.copy_(torch.randn(p.shape, generator=gen).div_(fan_in**0.5))  # one temporary, not two
        elif "norm" in name:
            p.copy_(1.0 + 0.2 * torch.randn(p.shape, generator=gen))
        else:
            p.copy_(0.2 * torch.randn(p.shape, generator=gen))
        done += p.numel()
        if progress is not None:
            progress(done / total)


class _Float64Torch(types.ModuleType):
    """`torch`, except that `torch.float32` is `torch.float64` (see `float64_casts`)."""

    def __init__(self):
        super().__init__("torch")
        self.float32 = torch.float64

    def __getattr__(self, name):
        return getattr(torch, name)


class float64_casts:
    """Within this context, the named modules' explicit casts to `torch.float32` cast to float64.

    LeRobot's SmolVLA code upcasts to float32 on purpose (RoPE, attention scores, the expert
    output) and Llama's RMSNorm computes in float32. Run on float64 weights and inputs, those
    casts would round the reference to float32 again. Swapping the module's `torch` name keeps
    LeRobot's code unchanged and makes it a true float64 computation.
    """

    def __init__(self, *modules):
        self.modules = modules
        self.saved = []

    def __enter__(self):
        proxy = _Float64Torch()
        for m in self.modules:
            self.saved.append((m, m.torch))
            m.torch = proxy
        return self

    def __exit__(self, *exc):
        for m, t in self.saved:
            m.torch = t
        self.saved.clear()
        return False


def store_vlm_in_bf16(path, exact=True):
    """Rewrite a `save_pretrained` model.safetensors with the VLM's tensors (BF16_PREFIX) in bf16.

    With `exact`, the values must already be bf16-representable, so the rewrite is lossless.
    """
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    with safe_open(str(path), "pt") as f:
        metadata = f.metadata()
    tensors = load_file(str(path))
    for k, v in tensors.items():
        if k.startswith(BF16_PREFIX):
            bf = v.to(torch.bfloat16)
            assert not exact or torch.equal(bf.float(), v), k
            tensors[k] = bf
    save_file(tensors, str(path), metadata=metadata)


def feature_stats(gen, dim, scale):
    """Random dataset statistics for one feature, with every field MEAN_STD and QUANTILES read."""
    mean = scale * torch.randn(dim, generator=gen)
    std = 0.5 + torch.rand(dim, generator=gen)
    return {
        "mean": mean,
        "std": std,
        "min": mean - 3 * std,
        "max": mean + 3 * std,
        "q01": mean - 2.3 * std,
        "q99": mean + 2.4 * std,
        "count": torch.tensor([1000]),
    }
