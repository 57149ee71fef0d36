"""The action modulation readout (protocols/gaia2_action_modulation.py): how far two commands move a GAIA-2 world
model's AdaLN vector and block modulations, read off the weights."""

from __future__ import annotations

import json

import pytest
import torch

from gaia_app.models.gaia2.conditioning import WorldConditions
from gaia_app.models.gaia2.latent_world_model import LatentWorldModel
from gaia_app.pipelines.gaia1_inputs import SPEED_PRESETS
from gaia_app.protocols.gaia2_action_modulation import action_modulation, modulation_contrast, step_actions
from tests.test_eval_latent_world_model import load_benchmark

pytestmark = pytest.mark.usefixtures("one_thread")
COMMANDS = [("brake", "straight"), ("accelerate", "straight"), ("keep", "left"), ("keep", "right")]


def trained_like_net() -> LatentWorldModel:
    """A tiny net with its adaLN-zero layers given random weights, as training leaves them."""
    torch.manual_seed(0)
    net = LatentWorldModel(latent_channels=8, dim=32, depth=2, heads=4, metadata_fields={"weather": 3})
    for layer in [*(block.modulation[-1] for block in net.blocks), net.modulation_out[-1]]:
        torch.nn.init.normal_(layer.weight, std=0.1)
    return net.eval()


def test_step_actions_average_each_latent_steps_frames_from_the_start_speed():
    actions = step_actions(COMMANDS, 10.0, steps=2, frames_per_step=4, rate=12.5)
    assert actions.shape == (4, 2, 2)
    accelerate = 10.0 + SPEED_PRESETS["accelerate"] * torch.arange(1, 9, dtype=torch.float64) / 12.5
    torch.testing.assert_close(actions[1, :, 0], accelerate.reshape(2, 4).mean(1))
    assert actions[0, 1, 0] < actions[0, 0, 0] < 10.0  # braking slows step by step
    torch.testing.assert_close(actions[2:, :, 0], torch.full((2, 2), 10.0, dtype=torch.float64))
    assert actions[2, 0, 1] == pytest.approx(0.02) and actions[3, 1, 1] == pytest.approx(-0.02)


def test_the_contrast_is_zero_for_equal_commands_and_where_the_embedding_ignores_a_channel():
    net = trained_like_net()
    same = step_actions(COMMANDS, 10.0, 2, 4, 12.5)[1]
    zero = modulation_contrast(net, same, same, [0.0, 0.5])
    assert zero["conditioner"].shape == (2, 2) and zero["blocks"].shape == (2, 2, 3)
    assert zero["conditioner"].abs().max() == 0 and zero["blocks"].abs().max() == 0
    readings = action_modulation(net, COMMANDS, [6.0, 12.0], 2, 4, 12.5, [0.0, 0.5])
    assert readings["speed"]["commands"] == ["accelerate/straight", "brake/straight"]
    assert len(readings["speed"]["blocks"]) == 2 and len(readings["speed"]["blocks"][0]) == 2  # [speed][τ][step][block]
    assert readings["curvature"]["commands"] == ["keep/left", "keep/right"]
    assert all(readings[name]["summary"][key]["min"] > 0 for name in readings for key in ("conditioner", "blocks_mean"))
    with torch.no_grad():  # the first action layer blind to the curvature half of the Fourier features
        net.conditioner.action[0].weight[:, net.conditioner.dim // 2:] = 0
    blind = action_modulation(net, COMMANDS, [6.0, 12.0], 2, 4, 12.5, [0.0, 0.5])
    assert blind["curvature"]["summary"]["blocks_mean"]["max"] == 0
    assert blind["speed"]["summary"]["blocks_mean"]["min"] > 0


def test_the_readout_recomputes_the_forward_pass_adaln_vector_and_its_changes_by_hand():
    """The readout's c is what `adaln` feeds the blocks; with 3 flow times and 2 steps (k ≠ g) every entry lands in
    its (τ, step, block) place, the relative change divides by the mid command's modulation, the absolute one not."""
    net = trained_like_net()
    actions = step_actions(COMMANDS, 10.0, 2, 4, 12.5)
    high, low, taus = actions[1], actions[0], [0.0, 0.4, 0.9]
    eye = torch.eye(3)[None].expand(1, 3, 3, 3)
    extrinsics = torch.eye(4)[None, None].expand(1, 3, 4, 4)
    cond = WorldConditions(eye, extrinsics, (32, 64), actions=high[None].float())
    with torch.no_grad():
        forward_c = net.conditioner.adaln(torch.full((1, 2), 0.4), cond, {"action": torch.ones(1, dtype=torch.bool)})
        c = {name: net.conditioner.tau_embedding(torch.tensor([[0.4]]))
             + net.conditioner.action_embedding(a.float())[None] for name, a in (("high", high), ("low", low))}
        c["mid"] = net.conditioner.tau_embedding(torch.tensor([[0.4]])) + net.conditioner.action_embedding(
            ((high + low) / 2).float())[None]
        block = net.blocks[1].modulation
        relative = (block(c["high"]) - block(c["low"])).norm(dim=-1) / block(c["mid"]).norm(dim=-1)
        absolute = (block(c["high"]) - block(c["low"])).norm(dim=-1)
    torch.testing.assert_close(forward_c, c["high"])
    reading = modulation_contrast(net, high, low, taus)
    assert reading["blocks"].shape == reading["blocks_change"].shape == (3, 2, 3) and reading["features"].shape == (2,)
    torch.testing.assert_close(reading["blocks"][1, :, 1], relative[0].double(), rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(reading["blocks_change"][1, :, 1], absolute[0].double(), rtol=1e-5, atol=1e-7)
    assert reading["features"][1] > reading["features"][0] > 0  # braking and accelerating diverge step by step


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="at least one start speed and one flow time"):
        action_modulation(trained_like_net(), COMMANDS, [], 2, 4, 12.5, [0.0])
    with pytest.raises(ValueError, match="every command has the same curvature"):
        action_modulation(trained_like_net(), COMMANDS[:2], [10.0], 2, 4, 12.5, [0.0])


def test_the_benchmark_reads_the_shipped_weights_and_writes_its_table(tmp_path):
    bench = load_benchmark("gaia2_action_modulation")
    result = bench.main(["--weights", "gaia2", "--start-speeds", "10", "--taus", "0.5", "--out", str(tmp_path)])
    reading = result["weights"]["gaia2"]
    assert set(reading) == {"speed", "curvature"}
    assert result["settings"]["generated_steps"] >= 1 and result["settings"]["rate"] > 0
    assert reading["curvature"]["summary"]["conditioner"]["mean"] > 0
    assert reading["speed"]["summary"]["features"]["mean"] > 0
    written = json.loads((tmp_path / "action_modulation.json").read_text())
    assert written["weights"]["gaia2"]["speed"]["commands"] == reading["speed"]["commands"]
    assert "| gaia2 | speed (" in (tmp_path / "action_modulation.md").read_text()
