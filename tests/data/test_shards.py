"""WebDataset shards (gaia_app/data/shard.py writes, gaia_app/data/shards.py streams): layout, atomic resumable
writing, every sample once per epoch across workers, exact mid-epoch resume, balanced acceptance, every kind."""

from __future__ import annotations

import collections
import io
import json
import tarfile
from pathlib import Path

import numpy as np
import pytest
import torch

from gaia_app.data.latent_cache import write_latent_clip
from gaia_app.data.shard import main as shard_main
from gaia_app.data.shard import parse_size, write_shards
from gaia_app.data.shard_datamodules import ClipShardDataModule, LatentShardDataModule, TokenShardDataModule
from gaia_app.data.shards import ShardLoader, shard_urls, split_shards
from gaia_app.data.token_cache import TokenSegment, find_segments, load_segment, write_segment
from tests.data.test_latent_cache import latent_clip

STEPS, SEQ, STRIDE = 20, 8, 4  # 4 windows per segment


def token_cache(root: Path, clips: int = 12, speeds: list[float] | None = None) -> Path:
    """`clips` clips × 2 cameras of random tokens with actions, timestamps and captions (a `.` in one clip's name)."""
    rng = np.random.default_rng(0)
    for c in range(clips):
        speed = speeds[c] if speeds else float(c)
        actions = np.stack([np.full(STEPS, speed), rng.normal(0, 0.01, STEPS)], 1).astype(np.float32)
        for camera in ("front", "left"):
            write_segment(root, TokenSegment(f"clip{c}{'.v2' if c == 3 else ''}/{camera}",
                                             rng.integers(0, 1000, (STEPS, 4, 6)), actions, np.arange(STEPS) * 0.16,
                                             [f"caption {c}"] * STEPS))
    return root


def window_ids(batches) -> list[tuple]:
    """A window's identity: its first tokens (random, so distinct per window)."""
    return [tuple(w.flatten()[:8].tolist()) for batch in batches for w in batch["tokens"]]


def folder_window_ids(cache: Path) -> list[tuple]:
    segments = [load_segment(p) for p in find_segments(cache)]
    return [tuple(s.tokens[i : i + SEQ].flatten()[:8].tolist())
            for s in segments for i in range(0, STEPS - SEQ + 1, STRIDE)]


@pytest.fixture(scope="module")
def tokens(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("tokens")
    cache = token_cache(root / "cache")
    write_shards("tokens", cache, root / "shards", shard_size=4000, val_fraction=0.25, progress=False)
    return cache, root / "shards"


def token_module(shards: Path, **kw) -> TokenShardDataModule:
    return TokenShardDataModule(str(shards), seq_len=SEQ, stride=STRIDE,
                                **{"batch_size": 5, "shuffle_buffer": 16, **kw})


def test_shard_layout_index_and_whole_clips_per_split(tokens) -> None:
    cache, shards = tokens
    index = json.loads((shards / "shards.json").read_text())
    assert index["kind"] == "tokens" and index["splits"]["train"]["samples"] + index["splits"]["val"]["samples"] == 24
    assert len(index["splits"]["train"]["shards"]) > 1
    keys = {}
    for split in ("train", "val"):
        for entry in index["splits"][split]["shards"]:
            with tarfile.open(shards / entry["name"]) as tar:
                names = tar.getnames()
            assert entry["samples"] == sum(n.endswith(".features.json") for n in names)
            for name in names:
                keys.setdefault(name.split("/")[0], set()).add(split)
    assert all(len(sides) == 1 for sides in keys.values())  # both cameras of a clip on one side
    assert "clip3%2Ev2" in keys  # a `.` in a name is escaped, so WebDataset's key split stays exact
    features = np.load(shards / "features-train.npz")
    assert set(features.files) == {"speed", "curvature"}
    assert len(features["speed"]) == index["splits"]["train"]["samples"]


@pytest.mark.parametrize("workers", [0, 2])
def test_an_epoch_streams_every_window_exactly_once(tokens, workers: int) -> None:
    cache, shards = tokens
    module = token_module(shards, num_workers=workers)
    train, val = list(module.train_dataloader()), list(module.val_dataloader())
    streamed = window_ids(train) + [tuple(w.flatten()[:8].tolist()) for b in val for w in b["tokens"][:, :SEQ]]
    assert max(collections.Counter(window_ids(train)).values()) == 1
    assert len(window_ids(train)) == 18 * 4  # 9 training clips × 2 cameras × 4 windows
    assert set(window_ids(train)) < set(folder_window_ids(cache))  # the same windows the folder loader cuts
    assert len(streamed) == len(set(streamed))
    batch = train[0]
    assert batch["tokens"].shape[1:] == (SEQ, 24) and batch["actions"].shape[1:] == (SEQ, 2)
    assert len(batch["text"][0]) == SEQ
    assert batch["tokens"].dtype == torch.int64  # widened in the main process after the int16 trip


def test_epochs_differ_in_order_and_replay_exactly_from_the_seed(tokens) -> None:
    _, shards = tokens
    loader = token_module(shards).train_dataloader()
    first, second = window_ids(loader), window_ids(loader)
    assert sorted(first) == sorted(second) and first != second  # a new shard order and buffer each epoch
    assert window_ids(token_module(shards).train_dataloader()) == first  # same seed, same stream


@pytest.mark.parametrize("workers", [0, 2])
def test_a_resumed_loader_neither_repeats_nor_skips(tokens, workers: int) -> None:
    _, shards = tokens
    full = window_ids(token_module(shards, num_workers=workers).train_dataloader())
    loader = token_module(shards, num_workers=workers).train_dataloader()
    taken = []
    for i, batch in enumerate(loader):
        taken.append(batch)
        if i == 6:
            state = loader.state_dict()
            break
    resumed = token_module(shards, num_workers=workers).train_dataloader()
    resumed.load_state_dict(json.loads(json.dumps(state)))  # what a checkpoint stores
    together = window_ids(taken) + window_ids(resumed)
    assert sorted(together) == sorted(full) and len(set(together)) == len(full)  # nothing repeated, nothing skipped
    if workers == 0:  # one stream: the very same order (with workers the loader restarts its round-robin at worker 0)
        assert together == full
    assert resumed.state_dict() == {"epoch": 1, "taken": [0] * max(1, workers)}  # the epoch is over


def test_a_folder_loaders_state_resumes_the_stream_at_its_epoch(tokens, caplog) -> None:
    _, shards = tokens
    loader = token_module(shards).train_dataloader()
    loader.load_state_dict({"epoch": 2, "items": 6, "batch_size": 3, "length": 30, "seed": 0})  # resumable.py's
    assert loader.epoch == 2 and "starts from its beginning" in caplog.text


def test_resuming_with_another_worker_count_is_refused(tokens) -> None:
    _, shards = tokens
    with pytest.raises(ValueError, match="keep the worker count"):
        token_module(shards, num_workers=2).train_dataloader().load_state_dict({"epoch": 0, "taken": [3]})


def test_epoch_batches_caps_every_epoch(tokens) -> None:
    _, shards = tokens
    loader = token_module(shards, epoch_batches=5).train_dataloader()
    assert [len(list(loader)) for _ in range(2)] == [5, 5] and loader.epoch == 2


def test_shards_split_by_rank_then_worker_cover_each_shard_once() -> None:
    urls = [f"s{i}" for i in range(7)]
    parts = [split_shards(urls, 3, 0, True, rank, 2, worker, 2) for rank in range(2) for worker in range(2)]
    assert sorted(u for part in parts for u in part) == urls


def test_balanced_acceptance_evens_out_speed_bins(tmp_path: Path) -> None:
    speeds = [1.0] * 9 + [20.0] * 3  # 3:1 slow to fast
    cache = token_cache(tmp_path / "cache", clips=12, speeds=speeds)
    write_shards("tokens", cache, tmp_path / "shards", shard_size=2000, progress=False)
    counts = collections.Counter()
    balance = {"features": {"speed": 2}, "exponent": 1.0}
    for seed in range(20):
        module = token_module(tmp_path / "shards", balance=balance, seed=seed, batch_size=1)
        counts.update(float(b["actions"][0, 0, 0]) for b in module.train_dataloader())
    assert 0.75 < counts[1.0] / counts[20.0] < 1.33  # about even (3.0 unbalanced)


def test_writing_is_resumable_and_refuses_another_plan(tokens, tmp_path: Path) -> None:
    cache, shards = tokens
    out = tmp_path / "again"
    write_shards("tokens", cache, out, shard_size=4000, val_fraction=0.25, progress=False)
    first = sorted(out.glob("*.tar"))
    before = {p.name: p.read_bytes() for p in first}
    first[1].unlink()  # as if the run died before this shard was renamed into place
    (out / f".{first[2].name}.partial").write_bytes(b"half")
    write_shards("tokens", cache, out, shard_size=4000, val_fraction=0.25, progress=False)
    assert {p.name: p.read_bytes() for p in sorted(out.glob("*.tar"))} == before  # deterministic bytes
    with pytest.raises(ValueError, match="planned from a different source"):
        write_shards("tokens", cache, out, shard_size=9000, val_fraction=0.25, progress=False)
    with pytest.raises(ValueError, match="--shard-size"):
        parse_size("lots")
    assert parse_size("256MB") == 256_000_000 and parse_size("1.5GB") == 1_500_000_000


def test_url_patterns_and_pipes_read_the_same_stream(tokens) -> None:
    _, shards = tokens
    names = sorted(p.name for p in shards.glob("train-*.tar"))
    pattern = f"{shards}/train-{{000000..{len(names) - 1:06d}}}.tar"
    assert shard_urls(pattern, "train")[0] == [str(shards / n) for n in names]
    piped = "::".join(f"pipe:cat {shards / n}" for n in names)
    expected = window_ids(token_module(str(shards)).train_dataloader())
    assert window_ids(token_module(piped, allow_pipe=True).train_dataloader()) == expected
    with pytest.raises(ValueError, match=r"'pipe:' URL runs its text as a shell command.*data\.allow_pipe=true"):
        token_module(piped).train_dataloader()
    with pytest.raises(FileNotFoundError, match="not found"):
        shard_urls(f"{shards}/nothing-{{0..1}}.tar", "train")


def test_latent_cache_shards_give_the_folder_windows(tmp_path: Path) -> None:
    for split, count in (("train", 5), ("val", 2)):
        for i in range(count):
            write_latent_clip(tmp_path / "latents" / split,
                              latent_clip(clip_id=f"{split}_{i}", meta={"weather": "rain" if i % 2 else "clear"}))
    shard_main([str(tmp_path / "latents"), str(tmp_path / "shards"), "--kind", "latents", "--shard-size", "20KB"])
    module = LatentShardDataModule(str(tmp_path / "shards"), steps=2, metadata_fields=["weather"], batch_size=2,
                                   num_workers=0)
    train = list(module.train_dataloader())
    assert sorted(c for b in train for c in b["clip_id"]) == [f"train_{i}" for i in range(5)]
    batch = train[0]
    assert (batch["mean"].shape[1:3] == (2, 2) and "agents_centre" in batch
            and batch["intrinsics"].shape[1:] == (2, 3, 3))
    val = list(module.val_dataloader())
    assert sorted(c for b in val for c in b["clip_id"]) == ["val_0", "val_1"]
    assert set(np.load(tmp_path / "shards" / "features-train.npz").files) == {"weather", "speed", "curvature"}


def test_clip_folder_shards_split_by_run_and_give_video_windows(tmp_path: Path) -> None:
    from gaia_app.data.clip_writer import write_clip
    from gaia_app.data.synthetic import generate_clip

    for seed in range(4):
        clip = generate_clip(seed=seed, height=32, width=56, cameras=["front"], clip_len=12, fps=25.0)
        clip.meta["run_id"] = f"drive{seed // 2}"  # two clips per drive
        write_clip(clip, tmp_path / "clips")
    index = write_shards("clips", tmp_path / "clips", tmp_path / "shards", shard_size="1MB", val_fraction=0.5,
                         split_by="run", progress=False)
    assert index["splits"]["train"]["samples"] == index["splits"]["val"]["samples"] == 2
    module = ClipShardDataModule(str(tmp_path / "shards"), clip_len=4, fps=12.5, height=32, width=56, batch_size=2)
    train, val = list(module.train_dataloader()), list(module.val_dataloader())
    runs = lambda batches: {m["run_id"] for b in batches for m in b["meta"]}  # noqa: E731
    assert len(runs(train)) == len(runs(val)) == 1 and runs(train) != runs(val)
    assert train[0]["video"].shape == (2, 1, 4, 3, 32, 56) and train[0]["actions"].shape == (2, 4, 2)


def test_missing_index_and_split_are_named(tmp_path: Path, tokens) -> None:
    with pytest.raises(FileNotFoundError, match="shards.json"):
        shard_urls(str(tmp_path), "train")
    with pytest.raises(Exception, match="no 'test' split"):
        shard_urls(str(tokens[1]), "test")
    assert isinstance(token_module(tokens[1]).train_dataloader(), ShardLoader)


def test_balancing_remote_shards_needs_their_index(tokens, tmp_path: Path) -> None:
    _, shards = tokens
    names = sorted(p.name for p in shards.glob("train-*.tar"))
    piped = "::".join(f"pipe:cat {shards / n}" for n in names)
    balance = {"features": {"speed": 2}, "exponent": 1.0}
    with pytest.raises(ValueError, match="data.index_dir"):
        token_module(piped, balance=balance, allow_pipe=True).train_dataloader()
    assert list(token_module(piped, balance=balance, index_dir=str(shards), allow_pipe=True).train_dataloader())
    with pytest.raises(ValueError, match=r"\['weather'\]: not in the shards' feature table"):
        token_module(shards, balance={"features": {"weather": None}, "exponent": 1.0}).train_dataloader()


def test_window_references_collate_to_the_folder_loaders_batch(tokens) -> None:
    from gaia_app.data.collate import collate_token_windows
    from gaia_app.data.shard_datamodules import collate_token_refs
    from gaia_app.data.token_cache import TokenWindows

    cache, _ = tokens
    segments = [load_segment(p) for p in find_segments(cache)[:3]]
    refs = [(segments[0], 4, SEQ), (segments[2], 0, SEQ), (segments[1], 12, SEQ)]
    items = [TokenWindows([seg], [(0, 0, STEPS)], SEQ, 1)[start] for seg, start, _ in refs]
    expected, got = collate_token_windows(items), collate_token_refs(refs)
    assert list(got) == list(expected) and got["text"] == expected["text"]
    for key in ("tokens", "actions", "timestamps"):
        assert got[key].dtype == expected[key].dtype and torch.equal(got[key], expected[key])
    segments[1].actions = None
    with pytest.raises(Exception, match="mixes windows with and without 'actions'"):
        collate_token_refs(refs)


def test_the_state_counts_batches_used_not_batches_fetched_ahead(tokens) -> None:
    _, shards = tokens
    full = window_ids(token_module(shards).train_dataloader())
    loader = token_module(shards).train_dataloader()
    batches = iter(loader)
    fetched = [next(batches) for _ in range(4)]  # Lightning fetches one batch ahead of its step
    for _ in range(3):
        loader.mark_used()
    assert loader.state_dict() == {"epoch": 0, "taken": [3]}
    resumed = token_module(shards).train_dataloader()
    resumed.load_state_dict(loader.state_dict())
    assert window_ids(fetched[:3]) + window_ids(resumed) == full  # the batch fetched but unused comes again


def test_http_urls_stream_like_local_shards(tokens) -> None:
    """Shards served over HTTP (WebDataset opens http(s):// through curl) give the same stream."""
    import functools
    import http.server
    import shutil
    import threading

    if shutil.which("curl") is None:
        pytest.skip("curl is not installed (WebDataset reads http:// through it)")
    _, shards = tokens
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(shards))
    handler.log_message = lambda *args: None
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        count = len(list(shards.glob("train-*.tar")))
        url = f"http://127.0.0.1:{server.server_address[1]}/{{split}}-{{000000..{count - 1:06d}}}.tar"
        streamed = window_ids(token_module(url).train_dataloader())
    finally:
        server.shutdown()
    assert streamed == window_ids(token_module(shards).train_dataloader())


def test_a_re_tokenized_source_is_refused_after_a_killed_run_unless_overwritten(tmp_path: Path) -> None:
    import json
    import os

    cache = token_cache(tmp_path / "cache", clips=4)
    (cache / "cache.json").write_text(json.dumps({"kind": "gaia1_tokens", "tokenizer_sha256": "old"}))
    out = tmp_path / "shards"
    write_shards("tokens", cache, out, shard_size=4000, progress=False)
    sorted(out.glob("*.tar"))[-1].unlink()  # killed before the last shard was renamed into place
    (cache / "cache.json").write_text(json.dumps({"kind": "gaia1_tokens", "tokenizer_sha256": "new"}))
    with pytest.raises(ValueError, match="re-written since.*--overwrite"):
        write_shards("tokens", cache, out, shard_size=4000, progress=False)
    (cache / "cache.json").write_text(json.dumps({"kind": "gaia1_tokens", "tokenizer_sha256": "old"}))
    segment = find_segments(cache)[0]
    os.utime(segment, ns=(segment.stat().st_atime_ns, segment.stat().st_mtime_ns + 10**9))  # re-written file
    with pytest.raises(ValueError, match="re-written since"):
        write_shards("tokens", cache, out, shard_size=4000, progress=False)
    index = write_shards("tokens", cache, out, shard_size=4000, progress=False, overwrite=True)
    assert sum(len(s["shards"]) for s in index["splits"].values()) == len(list(out.glob("*.tar")))


def test_camera_names_legal_for_clips_round_trip_through_shards(tmp_path: Path) -> None:
    from gaia_app.data.clip_writer import write_clip
    from gaia_app.data.synthetic import generate_clip

    for seed in range(2):
        clip = generate_clip(seed=seed, height=32, width=56, cameras=["front"], clip_len=12, fps=25.0)
        clip.cameras[0].name = "CAM_FRONT"
        write_clip(clip, tmp_path / "clips")
    assert all((folder / "CAM_FRONT.mp4").is_file() for folder in (tmp_path / "clips").iterdir())
    write_shards("clips", tmp_path / "clips", tmp_path / "shards", shard_size="1MB", progress=False)
    module = ClipShardDataModule(str(tmp_path / "shards"), clip_len=4, fps=12.5, height=32, width=56, batch_size=2,
                                 cameras=["CAM_FRONT"])
    batch = next(iter(module.train_dataloader()))
    assert batch["video"].shape == (2, 1, 4, 3, 32, 56)


def test_a_bad_sample_names_its_shard_and_index_and_can_be_skipped(tmp_path: Path) -> None:
    cache = token_cache(tmp_path / "cache", clips=4)
    out = tmp_path / "shards"
    write_shards("tokens", cache, out, shard_size="1MB", progress=False)
    shard = out / "train-000000.tar"
    with tarfile.open(shard) as tar:
        members = [(m, tar.extractfile(m).read()) for m in tar.getmembers()]
    broken = tmp_path / "broken.tar"
    with tarfile.open(broken, "w", format=tarfile.GNU_FORMAT) as tar:
        for member, data in members:
            if member.name.startswith("clip1/front.") and member.name.endswith("tokens.npy"):
                data = b"not a numpy file"
                member.size = len(data)
            tar.addfile(member, io.BytesIO(data))
    broken.replace(shard)
    with pytest.raises(Exception, match=r"train-000000\.tar: sample 2 \('clip1/front'\) cannot be read.*skip_bad"):
        list(token_module(out, shuffle_buffer=1).train_dataloader())
    kept = window_ids(token_module(out, shuffle_buffer=1, skip_bad_samples=True).train_dataloader())
    assert len(kept) == (4 * 2 - 1) * 4  # every window of the 7 good segments, none of the bad one
