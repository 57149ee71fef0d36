"""`python -m gaia_app.data.shard`: write WebDataset tar shards from clip folders, token caches or latent caches,
for streaming from object storage or a parallel filesystem (docs/data.md, "Sharded streaming").

One sample per clip (clip folders, latent caches) or per segment (token caches): the source's own files, unchanged,
named `<key>.<file>` inside the tar (a `/` in a file's relative path is written `%2F`, a `.` in a key `%2E`, so
WebDataset's key/extension split stays exact), plus `<key>.features.json`: the sample's row in the split's
feature table and its balancing features (GAIA-1 §3: mean speed and curvature, clip metadata).

Output folder:
    <split>-000000.tar …      shards of about --shard-size bytes each (a sample never spans two shards)
    features-<split>.npz      per split, one column per balancing feature, rows in sample order
    shards.json               kind, splits (shards with sample counts and bytes), the source's cache manifest
Splits: a latent cache's train/ and val/ become the train and val splits; a token cache or clip root is split here,
whole clips (token caches: every segment `<clip>/<camera>` of a clip together) or, for clip folders with
`--split-by run`, whole drives (data.split_by=run's rule, GAIA-1 §3).

Writes are atomic (each shard to a hidden temporary file, then renamed) and resumable: the plan (which sample goes
into which shard, and the size and modification time of every source file, and the source's cache manifest) is
stored in `.plan.json`; a rerun skips the shards already there only when the plan is the same, and refuses to
continue into a folder planned from a different or since re-written source (a cache re-tokenized after a killed
run would otherwise mix old and new shards under the new manifest); `--overwrite` removes the old shards and starts
clean. One writer per folder: the run holds the folder's lock (gaia_app/utils/locks.py).
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import re
import tarfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from gaia_app.data.clip import ClipError
from gaia_app.data.shard_format import INDEX, KINDS, PLAN, decode_name, encode_name, features_file, shard_name
from gaia_app.utils.locks import folder_lock
from gaia_app.utils.run_dir import atomic_write_bytes, atomic_write_text

SIZE_UNITS = {"": 1, "B": 1, "KB": 1e3, "MB": 1e6, "GB": 1e9}


@dataclass
class SampleSource:
    """One sample to write: its key and its files {name inside the sample: path on disk}, and its features."""

    key: str
    files: dict[str, Path]
    features: dict[str, Any] = field(default_factory=dict)

    @property
    def size(self) -> int:
        return sum(path.stat().st_size for path in self.files.values())


def parse_size(text: str) -> int:
    """'256MB' → 256_000_000 bytes (units B, KB, MB, GB; none: bytes)."""
    match = re.fullmatch(r"\s*([0-9.]+)\s*([KMG]?B?)\s*", str(text).upper())
    if not match or float(match.group(1)) <= 0:
        raise ValueError(f"--shard-size {text!r}: expected a positive size such as 256MB or 1GB")
    return int(float(match.group(1)) * SIZE_UNITS[match.group(2)])


def action_features(actions: np.ndarray | None) -> dict[str, float]:
    """Mean speed and curvature of a sample's (T, 2) actions (GAIA-1 §3 balances on both); none without actions."""
    if actions is None or len(actions) == 0:
        return {}
    return {"speed": float(np.mean(actions[:, 0])), "curvature": float(np.mean(actions[:, 1]))}


def token_samples(root: Path) -> list[SampleSource]:
    """Every segment of a token cache with its sidecars (gaia_app/data/token_cache.py)."""
    from gaia_app.data.token_cache import SIDECARS, find_segments, sidecar

    out = []
    for path in find_segments(root):
        name = path.relative_to(root).with_suffix("").as_posix() if root.is_dir() else path.stem
        files = {"tokens.npy": path}  # unpacked under these names, load_segment finds the sidecars again
        for suffix in SIDECARS:
            if sidecar(path, suffix).is_file():
                files[f"tokens{suffix}"] = sidecar(path, suffix)
        actions = np.load(files["tokens.actions.npy"]) if "tokens.actions.npy" in files else None
        out.append(SampleSource(encode_name(name), files, action_features(actions)))
    return out


def folder_files(folder: Path) -> dict[str, Path]:
    """Every file under a sample folder, by its relative path (hidden files and folders left out); a symbolic link
    leaving the folder is refused (its target would be packed into the shard)."""
    from gaia_app.data.clip_folder import check_no_escaping_links

    check_no_escaping_links(folder)
    files = {}
    for path in sorted(folder.rglob("*")):
        relative = path.relative_to(folder)
        if path.is_file() and not any(part.startswith(".") for part in relative.parts):
            files[encode_name(relative.as_posix(), slash=True)] = path
    return files


def latent_samples(root: Path) -> list[SampleSource]:
    """Every finished clip of one latent-cache split (gaia_app/data/latent_cache.py)."""
    from gaia_app.data.latent_cache import find_latent_clips

    out = []
    for folder in find_latent_clips(root):
        conditions = json.loads((folder / "conditions.json").read_text())
        actions = np.load(folder / "actions.npy") if (folder / "actions.npy").is_file() else None
        meta = {k: v for k, v in (conditions.get("meta") or {}).items() if isinstance(v, (str, int, float, bool))}
        out.append(SampleSource(encode_name(folder.name), folder_files(folder), {**meta, **action_features(actions)}))
    return out


def clip_samples(root: Path) -> tuple[list[SampleSource], Any]:
    """Every usable clip folder under `root` (gaia_app/data/clip_folder.py), and the dataset that found them."""
    from gaia_app.data.clip_folder import ClipFolderDataset, read_clip

    dataset = ClipFolderDataset(root)
    out = []
    for i, clip_id in enumerate(tqdm(dataset.clip_ids, desc="scan clips")):
        meta = {k: v for k, v in dataset.describe(i).items() if isinstance(v, (str, int, float, bool))}
        actions = read_clip(root / clip_id).actions if {"speed", "curvature"} - set(meta) else None
        out.append(SampleSource(encode_name(clip_id), folder_files(root / clip_id),
                                {**meta, **action_features(actions)}))
    return out, dataset


def split_samples(kind: str, root: Path, val_fraction: float, seed: int,
                  split_by: str) -> dict[str, list[SampleSource]]:
    """The splits to write (module docstring)."""
    if kind == "latents":
        splits = {name: latent_samples(root / name) for name in ("train", "val") if (root / name).is_dir()}
        if "train" not in splits:
            raise ClipError(f"latent cache '{root}': no train/ folder (write one with generate.py mode=encode)")
        return splits
    if not 0 <= val_fraction < 1:
        raise ValueError(f"--val-fraction {val_fraction}: expected a share in [0, 1)")
    if kind == "tokens":
        samples = token_samples(root)
        groups = [decode_name(s.key).split("/")[0] for s in samples]  # every camera of a clip on one side
    else:
        samples, dataset = clip_samples(root)
        groups = run_groups(dataset, split_by)
    if val_fraction == 0:
        return {"train": samples}
    names = sorted(set(groups))
    if len(names) < 2:
        raise ValueError(f"{root}: {len(samples)} samples from {len(names)} {split_by or 'clip'}; --val-fraction needs "
                         "at least two (or write --val-fraction 0 and shard a validation source separately)")
    order = np.random.default_rng(seed).permutation(len(names))
    held = {names[j] for j in order[: min(len(names) - 1, max(1, round(val_fraction * len(names))))]}
    return {"train": [s for s, g in zip(samples, groups) if g not in held],
            "val": [s for s, g in zip(samples, groups) if g in held]}


def run_groups(dataset: Any, split_by: str) -> list[str]:
    """The split group of every clip: its run (data.split_by=run, gaia_app/data/datamodules.clip_runs) or itself."""
    if split_by == "clip":
        return list(dataset.clip_ids)
    from gaia_app.data.datamodules import RUN_KEYS, clip_metadata, clip_runs

    return clip_runs(clip_metadata(dataset), RUN_KEYS)


def plan_shards(samples: Sequence[SampleSource], shard_size: int) -> list[list[int]]:
    """Consecutive samples packed into shards of about `shard_size` bytes (at least one sample each)."""
    shards: list[list[int]] = [[]]
    used = 0
    for i, sample in enumerate(samples):
        if shards[-1] and used + sample.size > shard_size:
            shards.append([])
            used = 0
        shards[-1].append(i)
        used += sample.size
    return shards if shards[0] else []


def write_tar(path: Path, samples: Iterable[SampleSource], rows: Iterable[int]) -> None:
    """An uncompressed tar of the samples' files and their features.json (fixed mtime: reruns give the same bytes),
    streamed to a hidden file beside `path` and renamed into place."""
    partial = path.with_name(f".{path.name}.partial")
    with tarfile.open(partial, mode="w", format=tarfile.GNU_FORMAT) as tar:
        for sample, row in zip(samples, rows):
            entries = {name: path.read_bytes() for name, path in sample.files.items()}
            entries["features.json"] = json.dumps({"row": row, **sample.features}).encode()
            for name, data in entries.items():
                info = tarfile.TarInfo(f"{sample.key}.{name}")
                info.size, info.mtime, info.mode = len(data), 0, 0o644
                tar.addfile(info, io.BytesIO(data))
    os.replace(partial, path)


def feature_table(samples: Sequence[SampleSource]) -> dict[str, np.ndarray]:
    """Columns of the features every sample has (a feature missing from some samples is left out)."""
    names = set.intersection(*(set(s.features) for s in samples)) if samples else set()
    return {name: np.asarray([s.features[name] for s in samples]) for name in sorted(names)}


def write_shards(kind: str, source: str | Path, out: str | Path, shard_size: int | str = "256MB",
                 val_fraction: float = 0.0, seed: int = 0, split_by: str = "clip", progress: bool = True,
                 overwrite: bool = False) -> dict[str, Any]:
    """Shard `source` into `out` (module docstring); returns the index written to shards.json. overwrite: remove the
    shards, plan, index and feature tables already in `out` first."""
    if kind not in KINDS:
        raise ValueError(f"--kind {kind!r}: expected one of {KINDS}")
    if split_by not in ("clip", "run"):
        raise ValueError(f"--split-by {split_by!r}: expected clip or run")
    size = parse_size(shard_size) if isinstance(shard_size, str) else int(shard_size)
    root, out = Path(source), Path(out)
    if not root.exists():
        raise FileNotFoundError(f"{root}: no such {kind} source")
    splits = split_samples(kind, root, val_fraction, seed, split_by)
    plans = {name: plan_shards(samples, size) for name, samples in splits.items()}
    manifest = root / "cache.json"
    cache = json.loads(manifest.read_text()) if manifest.is_file() else None
    with folder_lock(out, "out"):
        if overwrite:
            remove_shards(out)
        check_plan(out, kind, splits, plans, cache)
        return write_splits(out, kind, root, size, splits, plans, cache, progress)


def write_splits(out: Path, kind: str, root: Path, size: int, splits: dict[str, list[SampleSource]],
                 plans: dict[str, list[list[int]]], cache: dict[str, Any] | None, progress: bool) -> dict[str, Any]:
    """Every planned shard not on disk yet, the feature tables and shards.json; returns the index."""
    index: dict[str, Any] = {"format": 1, "kind": kind, "source": root.name, "shard_size": size, "splits": {}}
    if cache is not None:
        index["cache"] = cache
    for name, samples in splits.items():
        entries = []
        for number, members in enumerate(tqdm(plans[name], desc=f"shards {name}", disable=not progress)):
            path = out / shard_name(name, number)
            if not path.is_file():  # written whole or not at all: a shard on disk is finished
                write_tar(path, [samples[i] for i in members], members)
            entries.append({"name": path.name, "samples": len(members), "bytes": path.stat().st_size})
        buffer = io.BytesIO()
        np.savez(buffer, **feature_table(samples))
        atomic_write_bytes(out / features_file(name), buffer.getvalue())
        index["splits"][name] = {"samples": len(samples), "shards": entries, "features": features_file(name)}
    atomic_write_text(out / INDEX, json.dumps(index, indent=1))
    return index


def check_plan(out: Path, kind: str, splits: dict[str, list[SampleSource]], plans: dict[str, list[list[int]]],
               cache: dict[str, Any] | None = None) -> None:
    """Record the plan in out/.plan.json, or check that an interrupted run into `out` had the same one: the same
    samples in the same shards, made from the same files (size and modification time of each) of a source with
    the same cache manifest."""
    plan = {"kind": kind, "cache": cache,
            "splits": {name: [[sample_fingerprint(splits[name][i]) for i in members] for members in shards]
                       for name, shards in plans.items()}}
    digest = hashlib.sha256(json.dumps(plan, sort_keys=True).encode()).hexdigest()
    path = out / PLAN
    if path.is_file():
        found = json.loads(path.read_text()).get("sha256")
        if found != digest:
            raise ValueError(f"{out}: its shards were planned from a different source, a source re-written since "
                             f"(other files or another cache manifest), or another --shard-size/--val-fraction "
                             f"(plan {found} ≠ {digest}); pass --overwrite to start clean, or write into an empty "
                             "folder")
        return
    if out.is_dir() and any(out.glob("*.tar")):
        raise ValueError(f"{out}: holds shards but no {PLAN}; pass --overwrite to start clean, or write into an "
                         "empty folder")
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps({"sha256": digest}))


def sample_fingerprint(sample: SampleSource) -> list[Any]:
    """A sample's key and, per file, its name, size and modification time: a file re-written since the plan was
    made changes it."""
    stats = {name: path.stat() for name, path in sample.files.items()}
    return [sample.key, sorted((name, st.st_size, st.st_mtime_ns) for name, st in stats.items())]


def remove_shards(out: Path) -> None:
    """What an earlier run wrote into `out`: shards (finished or partial), plan, index and feature tables."""
    if not out.is_dir():
        return
    for path in [*out.glob("*.tar"), *out.glob(".*.partial"), *out.glob("features-*.npz"), out / PLAN, out / INDEX]:
        path.unlink(missing_ok=True)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m gaia_app.data.shard", description=__doc__.split("\n")[0])
    parser.add_argument("source", help="a clip root, a token cache (folder or .npy) or a latent cache root")
    parser.add_argument("out", help="the output folder (shards, features, shards.json)")
    parser.add_argument("--kind", required=True, choices=KINDS)
    parser.add_argument("--shard-size", default="256MB", help="target bytes per shard, e.g. 256MB (default), 1GB")
    parser.add_argument("--val-fraction", type=float, default=0.0,
                        help="clip roots and token caches: share of clips (or runs) written as the val split")
    parser.add_argument("--split-by", default="run", choices=("clip", "run"),
                        help="clip roots: hold out whole runs (default, the clips' run_id/source_video/sequence) "
                             "or clips")
    parser.add_argument("--seed", type=int, default=0, help="seed of the validation draw")
    parser.add_argument("--overwrite", action="store_true",
                        help="remove the shards an earlier run left in OUT and start clean (needed when the source "
                             "changed since)")
    args = parser.parse_args(argv)
    index = write_shards(args.kind, args.source, args.out, args.shard_size, args.val_fraction, args.seed,
                         args.split_by if args.kind == "clips" else "clip", overwrite=args.overwrite)
    for name, split in index["splits"].items():
        print(f"{name}: {split['samples']} samples in {len(split['shards'])} shards → {Path(args.out) / INDEX}")
    return index


if __name__ == "__main__":
    main()
