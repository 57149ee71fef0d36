"""Shared fixtures: the config directory, a Hydra compose helper, and the optional real data."""

from __future__ import annotations

import importlib.util
import os
import pathlib
from pathlib import Path
from types import ModuleType

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, open_dict

import gaia_app.utils.resolvers  # noqa: F401

ROOT = Path(__file__).resolve().parents[1]
CONF_DIR = ROOT / "conf"
SHARED_DATA = ROOT.parent / "shared" / "data"

os.environ.setdefault("RERUN", "on")
# Under pytest-xdist (`make test` runs one worker per core) each worker keeps to one thread: two workers of two
# threads each would fight over the cores. OMP_NUM_THREADS says so to the runs the tests start too (the thread
# policy of gaia_app/utils/threads.py reads it instead of counting free CPUs, and subprocesses inherit it).
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault("OMP_NUM_THREADS", "1")
torch.set_num_threads(1 if os.environ.get("PYTEST_XDIST_WORKER") else 2)


# The modules that take longest (seconds summed over their quick-tier tests, CI's `make test`, on a fresh clone,
# 2026-12-05: from 206 down to 15), collected first, with the slow tier's longest (the closed-loop pin in
# test_simulator.py, commaVQ, the sharded and multi-process runs) placed early for `make test-slow`: with `--dist
# loadscope --no-loadscope-reorder` (Makefile) each worker takes the next module in this order, so the long ones start
# early and the two workers finish together on the short ones instead of one running a long module alone at the end
# (xdist's own reorder puts modules with many tests first, not long ones). A stale list costs only balance, never a
# test.
LONGEST_MODULES = ["test_gaia2_generate.py", "test_simulator.py", "test_world_model_commavq.py", "test_shards_ddp.py",
                   "test_generate_rollouts.py",
                   "test_headline_claims.py", "test_configs.py", "test_train.py", "test_simulator_gym.py",
                   "test_eval_latent_world_model.py", "test_distributed.py", "test_agent_iou.py",
                   "test_video_decoder_training.py", "test_shipped_weights.py",
                   "test_controllability.py", "test_encode_latents.py", "test_road_users_weights.py",
                   "test_settings.py", "test_pandaset_chain.py", "test_vector_simulator.py",
                   "test_compiled_decode.py", "data/test_synthetic.py", "test_agent_futures.py",
                   "test_feature_distance.py", "test_agent_fidelity.py", "test_scaling.py",
                   "lit/test_gaia2_video_tokenizer.py", "lit/test_gaia1_tokenizer.py",
                   "test_shipped_gaia2_weights.py", "test_bench_simulator_step.py", "test_tokenize.py",
                   "test_hostile_inputs.py"]


def pytest_collection_modifyitems(config, items) -> None:
    rank = {f"tests/{name}": k for k, name in enumerate(LONGEST_MODULES)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(rank)))  # stable: the rest keep their order


# The first lines of a one-process DeepSpeed script run by a test: DeepSpeed would otherwise compile its shared-memory
# all-reduce op (a C++ build of about 2 minutes on a fresh 2-core machine, in every CI run), which one process never
# uses. By module name, as the attribute `deepspeed.comm.torch` is PyTorch itself.
DEEPSPEED_ONE_PROCESS = """import importlib
importlib.import_module("deepspeed.comm.torch").build_shm_op = lambda: None
"""

def load_benchmark(name: str) -> ModuleType:
    """benchmarks/<name>.py as a module (the scripts are not a package)."""
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def compose_config(config_name: str, overrides: list[str], output_dir: Path) -> DictConfig:
    """Compose like @hydra.main does, with hydra.runtime.output_dir set so ${hydra:...} resolves."""
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name=config_name, overrides=overrides, return_hydra_config=True)
    with open_dict(cfg):
        cfg.hydra.runtime.output_dir = str(output_dir)
        cfg.hydra.job.name = "test"
        cfg.paths.root_dir = str(ROOT)
    HydraConfig().set_config(cfg)
    return cfg


@pytest.fixture
def shared_data() -> Path:
    """../shared/data beside the project; tests using it skip cleanly when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent")
    return SHARED_DATA


TINY_TOKENIZER = ["experiment=gaia1/tokenizer_tiny", "trainer=tiny", "data=synthetic_frames_tiny",
                  "extras.print_config=false"]


@pytest.fixture(scope="session")
def tiny_tokenizer_ckpt(tmp_path_factory) -> Path:
    """last.ckpt of a 2-step tiny GAIA-1 tokenizer run, exactly as train.py writes it (once per test run)."""
    from tests.tiny_checkpoints import build_tokenizer, built_once, run_base, tokenizer_checkpoint

    return tokenizer_checkpoint(built_once(run_base(tmp_path_factory), "tiny-tokenizer", build_tokenizer))


@pytest.fixture(scope="session")
def genuine(tiny_tokenizer_ckpt: Path) -> Path:
    """A genuine training checkpoint, the starting point of the tampered ones (never edited in place)."""
    return tiny_tokenizer_ckpt


@pytest.fixture(scope="session")
def gaia1_tiny(tmp_path_factory) -> dict[str, Path]:
    """Tokenizer, world-model and video-decoder checkpoints of a tiny GAIA-1 chain at 32×48 (once per test run)."""
    from tests.tiny_checkpoints import build_gaia1, built_once, gaia1_checkpoints, run_base

    return gaia1_checkpoints(built_once(run_base(tmp_path_factory), "tiny-gaia1", build_gaia1))


@pytest.fixture(scope="session")
def gaia2_tiny(tmp_path_factory) -> dict[str, Path]:
    """Video-tokenizer and latent-world-model checkpoints and the latent cache of a tiny GAIA-2 chain (once per
    test run)."""
    from tests.tiny_checkpoints import build_gaia2, built_once, gaia2_checkpoints, run_base

    return gaia2_checkpoints(built_once(run_base(tmp_path_factory), "tiny-gaia2", build_gaia2))


class Payload:
    """Unpickling this calls Path.touch(marker): what a hostile checkpoint would smuggle in."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return pathlib.Path.touch, (pathlib.Path(self.marker),)


def tampered(genuine: Path, folder: Path, edit) -> Path:
    """A copy of the genuine checkpoint with `edit(checkpoint dict)` applied."""
    checkpoint = torch.load(genuine, weights_only=True)
    edit(checkpoint)
    path = folder / "tampered.ckpt"
    torch.save(checkpoint, path)
    return path


@pytest.fixture(scope="module")
def one_thread():
    """For modules of tiny nets: OpenMP barriers between 2 threads cost more than they save, and far more
    when another process keeps a core busy. Use with `pytestmark = pytest.mark.usefixtures("one_thread")`."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


CLIP_WIDTH, CLIP_PROJECTION = 32, 24  # the tiny CLIP's hidden size and text-embedding width


def save_tiny_clip(directory: Path) -> Path:
    """A tiny random CLIP text tower with projection and a character-level CLIP tokenizer, saved like a user's
    `save_pretrained` directory (the loading path of `CLIPTextEncoder`, with no download)."""
    import json

    from transformers import CLIPTextConfig, CLIPTextModelWithProjection, CLIPTokenizer

    directory.mkdir(parents=True, exist_ok=True)
    symbols = "abcdefghijklmnopqrstuvwxyz0123456789.,!?'-"
    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for symbol in symbols:
        vocab[symbol] = len(vocab)
        vocab[f"{symbol}</w>"] = len(vocab)
    (directory / "vocab.json").write_text(json.dumps(vocab))
    (directory / "merges.txt").write_text("#version: 0.2\n")
    CLIPTokenizer(str(directory / "vocab.json"), str(directory / "merges.txt")).save_pretrained(directory)
    torch.manual_seed(0)
    config = CLIPTextConfig(vocab_size=len(vocab), hidden_size=CLIP_WIDTH, intermediate_size=64, num_hidden_layers=2,
                            num_attention_heads=4, max_position_embeddings=77, projection_dim=CLIP_PROJECTION,
                            bos_token_id=0, eos_token_id=1, pad_token_id=1)
    CLIPTextModelWithProjection(config).save_pretrained(directory)
    return directory


@pytest.fixture(scope="session")
def tiny_clip_dir(tmp_path_factory) -> Path:
    return save_tiny_clip(tmp_path_factory.mktemp("clip"))


T5_WIDTH = 32  # the tiny T5's d_model


def save_tiny_t5(directory: Path, corpus: list[str]) -> Path:
    """A tiny random T5 encoder and a word-level tokenizer over `corpus` that appends </s> like T5's, saved like a
    user's `save_pretrained` directory."""
    from tokenizers import Tokenizer, models, pre_tokenizers, processors, trainers
    from transformers import PreTrainedTokenizerFast, T5Config, T5EncoderModel

    directory.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    config = T5Config(vocab_size=64, d_model=T5_WIDTH, d_kv=8, d_ff=64, num_layers=2, num_heads=4, pad_token_id=0,
                      eos_token_id=1, decoder_start_token_id=0)
    T5EncoderModel(config).save_pretrained(directory)
    tokenizer = Tokenizer(models.WordLevel(unk_token="<unk>"))
    tokenizer.pre_tokenizer = pre_tokenizers.Whitespace()
    tokenizer.train_from_iterator(corpus, trainers.WordLevelTrainer(special_tokens=["<pad>", "</s>", "<unk>"]))
    tokenizer.post_processor = processors.TemplateProcessing(single="$A </s>", special_tokens=[("</s>", 1)])
    PreTrainedTokenizerFast(tokenizer_object=tokenizer, pad_token="<pad>", eos_token="</s>",
                            unk_token="<unk>").save_pretrained(directory)
    return directory
