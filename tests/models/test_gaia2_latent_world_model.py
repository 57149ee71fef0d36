"""GAIA-2 latent world model network (GAIA-2 report, world model): shapes, conditioning routes, dropout, rigs."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from einops import rearrange

from gaia_app.data.synthetic.rig import build_rig
from gaia_app.models.gaia2.conditioning import CONDITIONS, AgentBoxes3d, WorldConditions, project_boxes
from gaia_app.models.gaia2.latent_world_model import LatentWorldModel

META = {"weather": 5, "time_of_day": 4}


def rig(cameras: int | list[str], height: int = 64, width: int = 112) -> tuple[torch.Tensor, torch.Tensor]:
    specs = build_rig(cameras, height, width)
    intrinsics = torch.from_numpy(np.stack([c.intrinsics for c in specs])).float()[None]
    extrinsics = torch.from_numpy(np.stack([c.extrinsics for c in specs])).float()[None]
    return intrinsics, extrinsics


def agents(t: int, centres: list[list[float]]) -> AgentBoxes3d:
    n = len(centres)
    return AgentBoxes3d(centre=torch.tensor(centres).expand(1, t, n, 3),
                        size=torch.tensor([4.5, 1.8, 1.6]).expand(1, t, n, 3),
                        yaw=torch.zeros(1, t, n), category=torch.zeros(1, t, n, dtype=torch.long),
                        mask=torch.ones(1, t, n, dtype=torch.bool))


def conditions(cameras: int = 3, t: int = 3, seed: int = 0) -> WorldConditions:
    g = torch.Generator().manual_seed(seed)
    k, e = rig(cameras)
    return WorldConditions(k, e, (64, 112), timestamps=torch.arange(t)[None].float() * 0.32,
                           actions=torch.randn(1, t, 2, generator=g),
                           agents=agents(t, [[15.0, 1.0, 0.8], [8.0, -3.0, 0.8]]),
                           metadata={"weather": torch.tensor([1]), "time_of_day": torch.tensor([2])},
                           text=torch.randn(1, 16, generator=g))


def model(**kw) -> LatentWorldModel:
    """A small model with every weight perturbed, so no zero-initialised path hides a condition."""
    torch.manual_seed(0)
    net = LatentWorldModel(**{**dict(latent_channels=8, dim=32, depth=2, heads=4, metadata_fields=META, text_dim=16),
                              **kw})
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return net.eval()


def latents(cameras: int = 3, t: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(1)
    return torch.randn(1, cameras, t, 8, 8, 14, generator=g), torch.rand(1, t, generator=g)


def test_output_shape_and_zero_initialised_velocity() -> None:
    x, tau = latents()
    fresh = LatentWorldModel(latent_channels=8, dim=32, depth=2, heads=4, metadata_fields=META, text_dim=16)
    out = fresh(x, tau, conditions())
    assert out.shape == x.shape and out.abs().max() == 0  # adaLN-Zero: an untrained model predicts v = 0
    assert model(patch_size=2)(x, tau, conditions()).shape == x.shape


@pytest.mark.parametrize("name", CONDITIONS)
def test_each_condition_changes_the_output_and_dropping_it_removes_the_effect(name: str) -> None:
    net, (x, tau), cond = model(), latents(), conditions()
    with torch.no_grad():
        full = net(x, tau, cond)
        dropped = net(x, tau, cond.without(name))
        absent = net(x, tau, WorldConditions(**{**cond.__dict__, {"action": "actions"}.get(name, name): None}))
    assert (full - dropped).abs().max() > 1e-4, f"{name} has no effect"
    torch.testing.assert_close(dropped, absent, atol=1e-6, rtol=0)


@pytest.mark.parametrize("name", CONDITIONS)
def test_training_dropout_of_a_condition_equals_its_absence(name: str) -> None:
    net, (x, tau), cond = model(), latents(), conditions()
    with torch.no_grad():
        expected = net(x, tau, cond.without(name))
        net.conditioner.dropout = {name: 1.0}
        net.conditioner.train()
        got = net(x, tau, cond)
    torch.testing.assert_close(got, expected, atol=1e-6, rtol=0)


def test_camera_geometry_and_timestamps_change_the_output() -> None:
    net, (x, tau), cond = model(), latents(), conditions()
    with torch.no_grad():
        base = net(x, tau, cond)
        moved = cond.extrinsics.clone()
        moved[:, 0, 0, 3] += 1.0
        other_rig = net(x, tau, WorldConditions(**{**cond.__dict__, "extrinsics": moved}))
        faster = net(x, tau, WorldConditions(**{**cond.__dict__, "timestamps": cond.timestamps * 0.5}))
    assert (base - other_rig).abs().max() > 1e-4 and (base - faster).abs().max() > 1e-4


@pytest.mark.parametrize("cameras", [1, 3, 5])
def test_one_model_serves_rigs_with_different_camera_counts(cameras: int) -> None:
    net = model()
    x, tau = latents(cameras)
    with torch.no_grad():
        out = net(x, tau, conditions(cameras))
    assert out.shape == x.shape and torch.isfinite(out).all()


def test_spatial_attention_spans_cameras() -> None:
    """Views are not independent: changing camera 0's latents moves camera 1's velocity."""
    net, (x, tau), cond = model(), latents(), conditions()
    y = x.clone()
    y[:, 0] += 1.0
    with torch.no_grad():
        a, b = net(x, tau, cond), net(y, tau, cond)
    assert (a[:, 1] - b[:, 1]).abs().max() > 1e-4


def test_token_subset_runs_on_those_tokens_only() -> None:
    """All positions reproduce the full forward; a subset gives its tokens only, attending among themselves."""
    net, (x, tau), cond = model(), latents(), conditions()
    with torch.no_grad():
        full = rearrange(net(x, tau, cond), "b v t c h w -> b t (v h w) c")
        every = net(x, tau, cond, positions=torch.arange(3 * 8 * 14))
        subset = net(x, tau, cond, positions=torch.tensor([0, 5, 130, 200]))
    torch.testing.assert_close(every, full, atol=1e-5, rtol=1e-5)
    assert subset.shape == (1, 3, 4, 8) and not torch.allclose(subset, full[:, :, [0, 5, 130, 200]])


def test_bad_shapes_are_named() -> None:
    net, (x, tau), cond = model(), latents(), conditions()
    with pytest.raises(ValueError, match=r"tau: expected \(b, t\) = \(1, 3\)"):
        net(x, tau[:, :2], cond)
    with pytest.raises(ValueError, match="intrinsics .* expected"):
        net(x[:, :2], tau, cond)
    with pytest.raises(ValueError, match=r"metadata\['weather'\]: expected .* in \[0, 5\)"):
        net(x, tau, WorldConditions(**{**cond.__dict__, "metadata": {"weather": torch.tensor([7])}}))
    with pytest.raises(ValueError, match="unknown conditions"):
        cond.without("weather")


def test_box_projection_into_the_rig() -> None:
    """A car 15 m ahead is centred in the front camera and out of the side ones; one behind is in no camera."""
    k, e = rig(["front", "front_left", "front_right"])
    boxes, depth, visible = project_boxes(agents(1, [[15.0, 0.0, 0.8], [-10.0, 0.0, 0.8]]), k, e, (64, 112))
    front = boxes[0, 0, 0, 0]
    assert visible[0, 0].tolist() == [[True, False], [False, False], [False, False]]
    assert float((front[0] + front[2]) / 2) == pytest.approx(0.5, abs=0.02)
    # far face: 15 m + half length − camera x
    assert float(depth[0, 0, 0, 0]) == pytest.approx(15.0 - 1.8 + 2.25, abs=0.3)
    assert boxes[0, 0, :, 1].abs().max() == 0  # invisible boxes are zeroed, not garbage


def test_cell_coverage_is_the_share_of_each_cell_under_the_box() -> None:
    from gaia_app.models.gaia2.conditioning import cell_coverage
    cover = cell_coverage(torch.tensor([0.125, 0.0, 0.5, 0.25]), (2, 4))  # x from half a cell to cell 2's end
    expected = torch.tensor([[0.25, 0.5, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]])  # the box spans half of row 0
    torch.testing.assert_close(cover, expected)
    assert cell_coverage(torch.zeros(4), (2, 4)).sum() == 0  # an invisible agent's zeroed box paints nothing


def test_agent_raster_paints_agents_where_their_boxes_fall_and_only_there() -> None:
    net, (x, _) = model(agent_raster=True), latents()
    near, far = conditions(), conditions()
    far.agents = agents(3, [[15.0, 1.0, 0.8], [-40.0, 0.0, 0.8]])  # the second agent moves behind the rig
    keep = net.conditioner.keep_masks(1, x.device)
    with torch.no_grad():
        features = net.conditioner.agent_features
        moved = (net.embed(x, near, keep, features(near))
                 - net.embed(x, far, keep, features(far))).abs().amax(dim=(0, 1, 3))
    gh, gw = 8 // net.patch, 14 // net.patch
    boxes, _, visible = project_boxes(near.agents, near.intrinsics, near.extrinsics, near.image_size)
    from gaia_app.models.gaia2.conditioning import cell_coverage
    covered = (cell_coverage(boxes[0, :, :, 1], (gh, gw)) * visible[0, :, :, 1, None, None]).amax(0) > 0  # (v, gh, gw)
    covered = rearrange(covered, "v h w -> (v h w)")
    assert covered.any() and (~covered).any()
    assert moved[covered].min() > 1e-4 and moved[~covered].max() < 1e-6


def test_agent_raster_is_dropped_with_the_agents() -> None:
    net, (x, tau), cond = model(agent_raster=True), latents(), conditions()
    plain = model()
    missing = net.load_state_dict(plain.state_dict(), strict=False).missing_keys  # same weights but the raster's
    assert missing and all(key.startswith("conditioner.agent_raster") for key in missing)
    with torch.no_grad():
        dropped = net(x, tau, cond.without("agents"))
        without_raster = plain(x, tau, cond.without("agents"))
    torch.testing.assert_close(dropped, without_raster, atol=1e-6, rtol=0)


def test_action_raster_steers_every_token_and_is_dropped_with_the_action() -> None:
    net, (x, tau), cond = model(action_raster=True), latents(), conditions()
    left, right = conditions(), conditions()
    left.actions = torch.tensor([[[10.0, 0.02]] * 3])
    right.actions = torch.tensor([[[10.0, -0.02]] * 3])
    keep = net.conditioner.keep_masks(1, x.device)
    with torch.no_grad():
        moved = (net.embed(x, left, keep) - net.embed(x, right, keep)).abs().amax(dim=-1)  # (1, t, n)
    heard = (moved > 1e-4).float()
    assert heard.mean() > 0.8  # every camera hears the turn, but for near ground clipped or gone in both futures
    assert heard.unflatten(-1, (3, 8, 14))[..., :4, :].all()  # the upper half of every camera, everywhere
    plain = model()
    missing = net.load_state_dict(plain.state_dict(), strict=False).missing_keys
    assert missing and all(key.startswith("conditioner.action_raster") for key in missing)
    with torch.no_grad():
        torch.testing.assert_close(net(x, tau, cond.without("action")), plain(x, tau, cond.without("action")),
                                   atol=1e-6, rtol=0)


def test_fresh_action_raster_starts_with_no_effect() -> None:
    x, _ = latents()
    fresh = LatentWorldModel(latent_channels=8, dim=32, depth=2, heads=4, metadata_fields=META, text_dim=16,
                             action_raster=True)
    keep = fresh.conditioner.keep_masks(1, x.device)
    cond = conditions()
    torch.testing.assert_close(fresh.embed(x, cond, keep), fresh.embed(x, cond.without("action"), keep))


def test_activation_checkpointing_in_training_gives_the_same_output_and_gradients() -> None:
    """checkpointing=True recomputes each block in the backward pass (the paper-size runs need it): in training
    mode, with the condition dropout's random draws repeated, output and gradients equal the plain model's."""
    x, tau = latents()
    results = []
    for checkpointing in (False, True):
        net = model(checkpointing=checkpointing).train()
        torch.manual_seed(3)
        out = net(x, tau, conditions())
        out.square().mean().backward()
        results.append((out.detach(), [p.grad.clone() for p in net.parameters() if p.grad is not None]))
    (plain, plain_grads), (checked, checked_grads) = results
    torch.testing.assert_close(checked, plain)
    assert len(plain_grads) == len(checked_grads) > 0
    for a, b in zip(plain_grads, checked_grads):
        torch.testing.assert_close(a, b)


def test_position_keys_carry_the_grid_code_at_the_box_centre_and_the_camera_embedding() -> None:
    from gaia_app.nn.spacetime import sincos_2d
    net, cond = model(agent_position_keys=True, patch_size=2), conditions()
    plain = model(patch_size=2)
    grid = (4, 7)
    with torch.no_grad():
        keyed, boxes, visible = net.conditioner.agent_features(cond, grid)
        unkeyed, _, _ = plain.conditioner.agent_features(cond)
        added = keyed - unkeyed  # same weights (seeded), so the difference is the key alone
        camera = net.conditioner.camera_embedding(cond)  # what every image token of a camera gets
    b, t, v, n = torch.nonzero(visible)[0].tolist()
    x0, y0, x1, y1 = boxes[b, t, v, n].tolist()
    row, col = (y0 + y1) / 2 * grid[0] - 0.5, (x0 + x1) / 2 * grid[1] - 0.5
    table = sincos_2d(*grid, net.dim)
    nearest = round(min(max(row, 0), grid[0] - 1)) * grid[1] + round(min(max(col, 0), grid[1] - 1))
    code = added[b, t, v, n] - camera[b, v]
    assert int((table - code).norm(dim=-1).argmin()) == nearest  # closest to the code of the cell under the centre
    with pytest.raises(ValueError, match="token grid"):
        net.conditioner.agent_features(cond)


def test_position_keys_change_the_velocity_only_through_the_agents() -> None:
    keyed, plain, (x, tau), cond = model(agent_position_keys=True), model(), latents(), conditions()
    with torch.no_grad():
        assert not torch.allclose(keyed(x, tau, cond), plain(x, tau, cond))
        torch.testing.assert_close(keyed(x, tau, cond.without("agents")), plain(x, tau, cond.without("agents")))


def queries_seen(net: LatentWorldModel, *args, **kwargs) -> torch.Tensor | None:
    """The query codes the first block receives in one forward of `net`."""
    seen = []
    handle = net.blocks[0].register_forward_pre_hook(lambda _m, inputs: seen.append(inputs[4]))
    with torch.no_grad():
        net(*args, **kwargs)
    handle.remove()
    return seen[0]


def test_position_queries_are_the_codes_the_image_tokens_carry() -> None:
    """agent_position_queries: each image token's query code is the grid code plus its camera's embedding, exactly
    what `embed` adds to that token (so it matches the key an agent over it gets), on a token subset too; it needs
    the keys."""
    from gaia_app.nn.spacetime import sincos_2d
    net, cond, (x, tau) = model(agent_position_keys=True, agent_position_queries=True), conditions(), latents()
    grid = (8, 14)
    with torch.no_grad():
        expected = rearrange(sincos_2d(*grid, net.dim)[None] + net.conditioner.camera_embedding(cond)[0][:, None],
                             "v n d -> 1 1 (v n) d")
        codes = net.position_codes(cond, grid)
        keep = net.conditioner.keep_masks(1, x.device)
        added = net.embed(x, cond, keep, None, codes) - net.embed(x, cond, keep, None, torch.zeros_like(codes))
    torch.testing.assert_close(queries_seen(net, x, tau, cond), expected)
    torch.testing.assert_close(added, expected.expand_as(added))
    positions = torch.tensor([0, 17, 200, 335])
    torch.testing.assert_close(queries_seen(net, x, tau, cond, positions=positions), expected[:, :, positions])
    assert queries_seen(model(agent_position_keys=True), x, tau, cond) is None
    with pytest.raises(ValueError, match="agent_position_keys"):
        model(agent_position_queries=True)


def test_position_queries_reach_only_the_cross_attention_queries() -> None:
    """In a block, a zero query code is no code, and a code changes only what the cross-attention adds; the model
    with the codes differs from the keys-only one on full and subset grids; checkpointing gives the same output."""
    from gaia_app.nn.spacetime import AdaLNSpaceTimeBlock
    torch.manual_seed(0)
    block = AdaLNSpaceTimeBlock(16, 4, 16).eval()
    x, c, context = torch.randn(1, 2, 5, 16), torch.randn(1, 2, 16), torch.randn(1, 2, 3, 16)
    with torch.no_grad():
        torch.testing.assert_close(block(x, c, context, None, torch.zeros(1, 1, 5, 16)), block(x, c, context))
        assert not torch.allclose(block(x, c, context, None, torch.randn(1, 1, 5, 16)), block(x, c, context))
    x, tau = latents()
    cond = conditions()
    positions = torch.tensor([0, 17, 200, 335])
    keys_only = model(agent_position_keys=True)
    queried = model(agent_position_keys=True, agent_position_queries=True)
    with torch.no_grad():
        assert not torch.allclose(queried(x, tau, cond), keys_only(x, tau, cond))
        assert not torch.allclose(queried(x, tau, cond, positions=positions),
                                  keys_only(x, tau, cond, positions=positions))
    checked = model(agent_position_keys=True, agent_position_queries=True, checkpointing=True).train()
    plain = model(agent_position_keys=True, agent_position_queries=True).train()
    checked.conditioner.dropout = plain.conditioner.dropout = {}
    torch.testing.assert_close(checked(x, tau, cond), plain(x, tau, cond))


def test_own_camera_coverage_pairs_each_token_with_the_agents_over_it_in_its_camera() -> None:
    from gaia_app.models.gaia2.conditioning import cell_coverage, own_camera_coverage
    net, cond, grid = model(), conditions(), (8, 14)
    _, boxes, visible = net.conditioner.agent_features(cond)
    own = own_camera_coverage(boxes, visible, grid)  # (1, t, v·cells, v·N)
    cover = (cell_coverage(boxes, grid) > 0) & visible[..., None, None]
    v, n, cells = boxes.shape[2], boxes.shape[3], grid[0] * grid[1]
    assert own.shape == (1, 3, v * cells, v * n) and own.any()
    for t in range(3):
        for camera in range(v):
            for agent_camera in range(v):
                block = own[0, t, camera * cells:(camera + 1) * cells, agent_camera * n:(agent_camera + 1) * n]
                expected = rearrange(cover[0, t, camera], "n h w -> (h w) n") if camera == agent_camera else False
                assert torch.equal(block, torch.as_tensor(expected).expand_as(block))


def test_box_attention_lets_a_token_read_only_the_agents_over_it() -> None:
    """agent_box_attention: in the first block, the cross-attention output of a token no box covers is the same
    with the agents as without them; under a box it changes. The same holds on a token subset (the selective pass)."""
    from gaia_app.models.gaia2.conditioning import own_camera_coverage
    net, cond, (x, tau) = model(agent_box_attention=True), conditions(), latents()
    _, boxes, visible = net.conditioner.agent_features(cond)
    covered = rearrange(own_camera_coverage(boxes, visible, (8, 14)).any(-1), "b t n -> (b t) n")
    assert covered.any() and not covered.all()
    step = 0
    positions = torch.cat([torch.nonzero(covered[step])[:3, 0], torch.nonzero(~covered[step])[:3, 0]])
    outputs = []
    handle = net.blocks[0].cross.register_forward_hook(lambda _m, _i, out: outputs.append(out))
    with torch.no_grad():
        for subset in (None, positions):
            net(x, tau, cond, positions=subset)
            net(x, tau, cond.without("agents"), positions=subset)
    handle.remove()
    with_agents, without, subset_with, subset_without = outputs
    torch.testing.assert_close(with_agents[~covered], without[~covered])
    assert not torch.allclose(with_agents[covered], without[covered])
    torch.testing.assert_close(subset_with[step, 3:], subset_without[step, 3:])  # the uncovered three
    assert not torch.allclose(subset_with[step, :3], subset_without[step, :3])


def test_cross_attention_per_query_mask_equals_the_shared_mask_when_rows_agree() -> None:
    from gaia_app.nn.spacetime import CrossAttention
    torch.manual_seed(0)
    attn = CrossAttention(16, 16, 4).eval()
    x, context = torch.randn(2, 5, 16), torch.randn(2, 7, 16)
    mask = torch.rand(2, 7) > 0.4
    mask[:, 0] = True
    with torch.no_grad():
        torch.testing.assert_close(attn(x, context, mask[:, None].expand(2, 5, 7)), attn(x, context, mask))
