"""Where the action (or text) signal of GAIA-1 world models goes, side by side on the same held-out windows (issue
50, item 2).

    python -m gaia_app.protocols.action_signal_report --tokens <cache root> --out <dir> \
        --model shipped=gaia_app/weights/gaia1 --model paper=outputs/.../checkpoints/last.ckpt
    python -m gaia_app.protocols.action_signal_report --stream text ...   # the captions instead of the actions

Each --model is NAME=PATH: a weights folder (with world_model.yaml) or a world-model training checkpoint. The
windows are the first --windows non-overlapping windows of the model's T steps from the cache's val/ split (the
held-out world of generate.py mode=tokenize), scored in batches of --batch. The statistics are those of
gaia_app/eval/action_signal.py (attention mass on action tokens per layer and head, the actions' write into the
residual stream, the counterfactual share, input gradients, KL of the prediction). With --stream text the same
statistics are taken of the text tokens: each window's own captions, encoded by the model's own text encoder (the
weights folder's `text_encoder`, or the checkpoint's), with the actions held at their null embedding. Writes
action_signal.json and action_signal.md (text_signal.* for --stream text) into --out; docs/paper_faithful.md reads
them.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from gaia_app.data.collate import collate_token_windows
from gaia_app.eval.action_signal import STREAMS, action_signal, markdown
from gaia_app.models.gaia1.world_model import WorldModel
from gaia_app.protocols.world_model_report import windows
from gaia_app.utils.named_paths import parse_named_paths
from gaia_app.utils.run_dir import atomic_write_text


def load_world_model(path: Path) -> tuple[WorldModel, torch.nn.Module | None]:
    """The GAIA-1 world-model net of a weights folder or of a training checkpoint (float32, eval mode), and its text
    encoder (None if it has none)."""
    if path.is_dir():
        from gaia_app.weights.folders import load_nets

        nets, _ = load_nets(path, "world_model", "cpu")
        net, text_encoder = nets["net"], nets.get("text_encoder")
    else:
        from gaia_app.lit.checkpoint import load_module

        module = load_module(path)
        net, text_encoder = getattr(module, "world_model", None), getattr(module, "text_encoder", None)
    if not isinstance(net, WorldModel):
        raise TypeError(f"--model {path}: expected a GAIA-1 world model (weights folder or checkpoint), "
                        f"got {type(net).__name__}")
    return net.float().eval(), (text_encoder.float().eval() if text_encoder is not None else None)


def parse_models(specs: list[str]) -> dict[str, Path]:
    return parse_named_paths(specs, "--model")


def window_batches(root: Path, net: WorldModel, count: int, batch: int, text_encoder: torch.nn.Module | None = None
                   ) -> Iterator[tuple[torch.Tensor, ...]]:
    """(tokens (b, T, n), actions (b, T, l)) of the first `count` windows of root/val, and with a text encoder their
    encoded captions (b, T, m, e) as a third element."""
    val = windows(root / "val", net.frames)
    if len(val) == 0:
        raise ValueError(f"--tokens {root}: val/ holds no window of {net.frames} steps")
    count = min(count, len(val))
    for start in tqdm(range(0, count, batch), desc="action signal", unit="batch"):
        items = collate_token_windows([val[i] for i in range(start, min(start + batch, count))])
        if "actions" not in items:
            raise ValueError(f"--tokens {root}: its windows carry no actions")
        if items["tokens"].shape[2] != net.n:
            raise ValueError(f"--tokens {root}: {items['tokens'].shape[2]} tokens per frame, the model expects "
                             f"{net.n}")
        if text_encoder is None:
            yield items["tokens"].long(), items["actions"].float()
            continue
        if "text" not in items:
            raise ValueError(f"--tokens {root}: its windows carry no captions (--stream text needs them)")
        with torch.no_grad():
            text = text_encoder(items["text"]).float()
        yield items["tokens"].long(), items["actions"].float(), text


def report(models: dict[str, Path], tokens: Path, count: int, batch: int, stream: str = "actions") -> dict[str, Any]:
    results = {}
    for name, path in models.items():
        net, text_encoder = load_world_model(path)
        if stream == "text" and text_encoder is None:
            raise ValueError(f"--model {name}: {path} has no text encoder, so --stream text has nothing to read")
        batches = window_batches(tokens, net, count, batch, text_encoder if stream == "text" else None)
        results[name] = action_signal(net, batches, stream) | {"path": str(path)}
    return results


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", action="append", required=True, help="NAME=PATH (weights folder or checkpoint)")
    parser.add_argument("--tokens", type=Path, required=True, help="token cache root with val/")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--windows", type=int, default=16)
    parser.add_argument("--batch", type=int, default=2)
    parser.add_argument("--stream", choices=STREAMS, default="actions", help="the conditioning stream to follow")
    args = parser.parse_args(argv)
    results = report(parse_models(args.model), args.tokens, args.windows, args.batch, args.stream)
    text = "\n".join(markdown(r, name) for name, r in results.items())
    stem = "action_signal" if args.stream == "actions" else "text_signal"
    atomic_write_text(args.out / f"{stem}.json", json.dumps(results, indent=2))
    atomic_write_text(args.out / f"{stem}.md", text)
    print(text)
    return results


if __name__ == "__main__":
    main()
