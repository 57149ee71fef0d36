"""benchmarks/gaia2_agent_attention.py: where the agents' cross-attention looks and what the agents change."""

from __future__ import annotations

from pathlib import Path

import torch

from benchmarks.gaia2_agent_attention import markdown, pooled, window_report
from gaia_app.data.latent_cache import read_latent_clip
from gaia_app.data.latent_windows import collate_latent_windows, latent_window
from gaia_app.data.metadata import MetadataEncoder
from gaia_app.models.gaia2.conditioning import batch_conditions
from gaia_app.models.gaia2.latent_world_model import LatentWorldModel
from tests.test_flow_gain import META, cache


def perturbed(**kw) -> LatentWorldModel:
    torch.manual_seed(0)
    net = LatentWorldModel(latent_channels=8, dim=32, depth=2, heads=4, metadata_fields=META, **kw)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return net.eval()


def window(root: Path, net: LatentWorldModel) -> tuple[torch.Tensor, object]:
    clip = read_latent_clip(sorted(p for p in root.iterdir() if p.is_dir())[0])
    batch = collate_latent_windows([latent_window(clip, 0, 4, MetadataEncoder(list(net.conditioner.metadata_fields)))])
    return batch["mean"], batch_conditions(batch, None)


def test_masses_are_shares_and_the_raster_acts_inside_the_boxes(tmp_path: Path) -> None:
    root = cache(tmp_path / "val")
    rows = {}
    for raster in (False, True):
        net = perturbed(agent_raster=raster)
        rows[raster] = row = window_report(net, *window(root, net), noise_seed=0)
        assert row is not None and len(row["blocks"]) == 2
        for block in row["blocks"]:
            assert 0 <= block["own_inside"] <= block["inside"] <= 1 and 0 <= block["outside"] <= 1
            assert 0 < block["uniform"] < 1  # one visible agent among the null token, metadata and agents
        assert row["effect_inside"] > 0
    ratio = {raster: r["effect_inside"] / r["effect_outside"] for raster, r in rows.items()}
    # painted agents change the tokens they cover more than the rest, which spatial attention reaches afterwards
    assert ratio[True] > 1.3 and ratio[True] > 1.2 * ratio[False]
    table = markdown([{"weights": "w", **pooled([rows[True], rows[True]])}])
    assert "| w | 1 |" in table and "effect of the agents" in table


def test_a_net_with_position_keys_is_read_too(tmp_path: Path) -> None:
    net = perturbed(agent_position_keys=True)
    row = window_report(net, *window(cache(tmp_path / "val"), net), noise_seed=0)
    assert row is not None and row["effect_inside"] > 0


def test_a_window_without_visible_agents_is_skipped(tmp_path: Path) -> None:
    net = perturbed()
    x, cond = window(cache(tmp_path / "val"), net)
    cond.agents = None
    assert window_report(net, x, cond, noise_seed=0) is None


def test_box_attention_puts_no_mass_outside_the_boxes_and_its_uniform_share_counts_only_the_keys_it_reads(
        tmp_path: Path) -> None:
    root = cache(tmp_path / "val")
    rows = {}
    for masked in (False, True):
        net = perturbed(agent_box_attention=masked)
        rows[masked] = window_report(net, *window(root, net), noise_seed=0)
    for block in rows[True]["blocks"]:
        assert block["outside"] == 0 and block["own_inside"] == block["inside"] > 0
    for masked_block, plain_block in zip(rows[True]["blocks"], rows[False]["blocks"]):
        assert 0 < masked_block["uniform"] <= plain_block["uniform"]
