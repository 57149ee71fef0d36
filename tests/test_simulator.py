"""The closed-loop driving simulator (issue 25, items 1 and 4) on the shipped GAIA-1 reference weights."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from gaia_app.pipelines.gaia1 import Gaia1Pipeline
from gaia_app.pipelines.simulator import DrivingSimulator
from gaia_app.weights.folders import shipped_folder

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def pipeline() -> Gaia1Pipeline:
    return Gaia1Pipeline.from_weights(shipped_folder("gaia1"), video_decoder=False)


def test_spaces_and_episode_follow_the_gymnasium_api(pipeline: Gaia1Pipeline) -> None:
    env = DrivingSimulator(pipeline, context_frames=4, max_steps=3)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs) and obs.shape == (64, 112, 3) and info["step"] == 0
    env.action_space.seed(0)
    assert env.action_space.shape == (2,) and env.action_space.contains(env.action_space.sample())
    for k in range(3):
        obs, reward, terminated, truncated, info = env.step([10.0, 0.02])
        assert env.observation_space.contains(obs) and reward == 0.0 and not terminated
        assert truncated == (k == 2) and info["step"] == k + 1 and info["action"] == pytest.approx([10.0, 0.02])
    assert np.array_equal(env.render(), obs)


def test_steps_are_deterministic_under_a_seed(pipeline: Gaia1Pipeline) -> None:
    def episode(seed: int) -> list[np.ndarray]:
        env = DrivingSimulator(pipeline)
        env.reset(seed=seed, options={"index": 1})
        return [env.step([8.0, -0.02])[4]["tokens"] for _ in range(3)]

    first, again, other = episode(3), episode(3), episode(4)
    assert all(np.array_equal(a, b) for a, b in zip(first, again))
    assert not all(np.array_equal(a, b) for a, b in zip(first, other))


def closed_and_open(pipeline: Gaia1Pipeline, steps: int, seed: int = 7) -> tuple[torch.Tensor, torch.Tensor, list]:
    """A closed-loop episode of `steps` steps from 4 context frames, the open-loop rollout of its actions, and the
    positions of every world-model forward of the episode."""
    env = DrivingSimulator(pipeline, context_frames=4)
    env.reset(seed=seed)
    context = env.tokens.clone()
    rng = np.random.default_rng(seed)
    commands = [[float(rng.uniform(6, 14)), float(rng.uniform(-0.03, 0.03))] for _ in range(steps)]
    net, calls = pipeline.world_model, []
    decode = net.decode
    net.decode = lambda x, cache=None: calls.append(x.shape[1]) or decode(x, cache)
    try:
        closed = torch.stack([torch.from_numpy(env.step(a)[4]["tokens"]) for a in commands])
    finally:
        del net.decode
    actions = torch.from_numpy(np.stack(env.actions))[None]
    opened, _ = pipeline.sample_batch(context[None], steps, None, actions, None, 1, torch.Generator().manual_seed(seed))
    return closed, opened[0, 4:].cpu(), calls


def test_a_closed_loop_episode_reproduces_the_open_loop_rollout_of_its_actions(pipeline: Gaia1Pipeline) -> None:
    """The episode keeps one sampling session: token for token the open-loop rollout, through 3 window slides
    (learned step embeddings: each slide re-prefills the window, every other step feeds one frame's positions)."""
    window = int(pipeline.world_model.frames)
    closed, opened, calls = closed_and_open(pipeline, window - 4 + 3)
    assert torch.equal(closed, opened)
    edge = pipeline.world_model.m + 2 + 1  # the last frame's last token and actions, then the new step's text
    assert sum(c > edge for c in calls) == 1 + 3  # the context's prefill, then one re-prefill per slide


def test_with_rotary_time_no_step_re_prefills(pipeline: Gaia1Pipeline) -> None:
    """A world model with relative time (random weights, the shipped layout): through window slides too, each
    step feeds the cache one frame's positions, and the episode still equals the open-loop rollout."""
    from gaia_app.models.gaia1.world_model import WorldModel

    shipped = pipeline.world_model
    torch.manual_seed(0)
    net = WorldModel(shipped.vocab_size, dim=32, depth=2, heads=4, frames=6, text_tokens=shipped.m,
                     image_tokens=shipped.n, text_dim=8, action_deltas=True, temporal_encoding="rope").eval()
    rope = Gaia1Pipeline(pipeline.tokenizer, net, pipeline.image_size, rate=pipeline.rate)
    closed, opened, calls = closed_and_open(rope, 6, seed=3)
    assert torch.equal(closed, opened)
    assert max(calls[1:]) <= net.m + 2 + 1  # after the context's prefill: one step's edge at most


def test_a_guided_prompted_episode_reproduces_the_guided_open_loop_rollout(pipeline: Gaia1Pipeline) -> None:
    """reset's guidance option (GAIA-1 §5.1 eq. 3) with a prompt: the episode equals the open-loop rollout of a
    pipeline built with that guidance, fed the same prompt and actions."""
    from gaia_app.diffusion.guidance import ClassifierFreeGuidance

    env = DrivingSimulator(pipeline, context_frames=4)
    env.reset(seed=5, options={"prompt": "It is night.", "guidance": 2.0})
    context = env.tokens.clone()
    closed = torch.stack([torch.from_numpy(env.step(a)[4]["tokens"]) for a in ([9.0, 0.0], [11.0, 0.02], [12.0, 0.0])])
    guided = Gaia1Pipeline(pipeline.tokenizer, pipeline.world_model, pipeline.image_size, pipeline.text_encoder,
                           guidance=ClassifierFreeGuidance(2.0), rate=pipeline.rate)
    text = guided.encode_text_batch([["It is night."] * 7])
    actions = torch.from_numpy(np.stack(env.actions))[None]
    opened, _ = guided.sample_batch(context[None], 3, text, actions, None, 1, torch.Generator().manual_seed(5))
    assert torch.equal(closed, opened[0, 4:].cpu())
    unguided = DrivingSimulator(pipeline, context_frames=4)
    unguided.reset(seed=5, options={"prompt": "It is night.", "guidance": 0})
    assert unguided.guidance is None and not torch.equal(
        torch.from_numpy(unguided.step([9.0, 0.0])[4]["tokens"]), closed[0])
    for bad in (-1.0, float("nan"), "strong"):
        with pytest.raises(ValueError, match="reset option guidance"):
            env.reset(options={"guidance": bad})


def test_observations_through_the_video_decoder_at_25_hz(pipeline: Gaia1Pipeline) -> None:
    """observation='video_decoder': four frames per step (6.25 → 25 Hz), each step's new frame decoded with the
    frames before it as context; decoding has its own noise, so the episode's tokens are those of tokenizer
    observations under the same seed."""
    with_decoder = Gaia1Pipeline.from_weights(shipped_folder("gaia1"), video_decoder=True, decoder_steps=1)
    env = DrivingSimulator(with_decoder, observation="video_decoder")
    plain = DrivingSimulator(pipeline)
    assert env.observation_space.shape == (4, 64, 112, 3)
    obs, _ = env.reset(seed=2)
    plain.reset(seed=2)
    assert env.observation_space.contains(obs)
    for action in ([10.0, 0.0], [12.0, 0.02]):
        obs, *_, info = env.step(action)
        assert env.observation_space.contains(obs) and obs.std() > 5  # a picture, not a constant
        assert np.array_equal(info["tokens"], plain.step(action)[4]["tokens"])
    assert len(env.observer.base) == 6  # 4 context frames and 2 steps decoded at 6.25 Hz
    with pytest.raises(ValueError, match="needs a pipeline with a video decoder"):
        DrivingSimulator(pipeline, observation="video_decoder")
    with pytest.raises(ValueError, match="observation='video'"):
        DrivingSimulator(pipeline, observation="video")


def test_steps_build_no_autograd_graph_and_keep_their_streams(pipeline: Gaia1Pipeline) -> None:
    """The session's cache and conditions carry no graph (weights loaded for inference still require grad), and a
    step cannot bring streams the episode was not opened with."""
    env = DrivingSimulator(pipeline)
    env.reset(seed=0)
    env.step([10.0, 0.0])
    env.step([10.0, 0.01])
    keys, values = env.session.stream.cache.buffers[0]
    assert not (keys.requires_grad or values.requires_grad or env.session.streams.actions.requires_grad)
    with pytest.raises(ValueError,
                       match=r"opened with streams \('actions',\); these steps bring \('text', 'actions'\)"):
        pipeline.rollouts.extend_session(env.session, torch.zeros(1, 2, 2), text=torch.zeros(1, 2, 4, 64))


def test_bad_actions_are_named(pipeline: Gaia1Pipeline) -> None:
    """A few cases; the full table of refusals is in tests/test_simulator_gym.py."""
    env = DrivingSimulator(pipeline, max_steps=2)
    with pytest.raises(RuntimeError, match="reset"):
        env.step([5.0, 0.0])
    env.reset(seed=0)
    for action, match in (([float("nan"), 0.0], "finite"), ([1.0, 2.0, 3.0], r"shape \(3,\)"),
                          ([90.0, 0.0], r"speed must lie in \[0, 70\] m/s")):
        with pytest.raises(ValueError, match=match):
            env.step(action)
    with pytest.raises(TypeError, match="two numbers"):
        env.step(["fast", 0.0])
    with pytest.raises(ValueError, match="context='none' .* give prompt"):
        env.reset(options={"context": "none"})
    with pytest.raises(ValueError, match="reset options"):
        env.reset(options={"weather": "snow"})


def test_an_episode_can_start_from_a_prompt_alone(pipeline: Gaia1Pipeline) -> None:
    env = DrivingSimulator(pipeline, max_steps=2)
    obs, info = env.reset(seed=1, options={"context": "none", "prompt": "It is night."})
    assert env.observation_space.contains(obs) and len(env.tokens) == 1
    obs, *_ = env.step([8.0, 0.0])
    assert len(env.tokens) == 2


def test_the_filter_averages_out_probe_noise() -> None:
    """Noisy probe readings (std 2.5 m/s) around a constant true speed of 12 m/s, the command constant: over the
    last 100 of 200 steps the filter's estimate is off by less than a third of what the raw readings are, and a
    change of the command moves the estimate by that change before any reading confirms it (the plant model)."""
    from gaia_app.tasks.drive import SpeedFilter

    rng = np.random.default_rng(0)
    readings = 12.0 + 2.5 * rng.standard_normal(200)
    speed_filter = SpeedFilter(process_noise=0.3, probe_noise=2.5)
    speed_filter.start(8.0)  # the context's speed, 4 m/s off
    estimates = np.array([speed_filter.update(0.0, z) for z in readings])
    raw_error, filtered_error = np.abs(readings[100:] - 12).mean(), np.abs(estimates[100:] - 12).mean()
    assert filtered_error < raw_error / 3, (filtered_error, raw_error)
    before = speed_filter.estimate
    after = speed_filter.update(2.0, before + 2.0)  # the reading agrees with the predicted speed
    assert after == pytest.approx(before + 2.0)


def test_the_controller_commands_from_the_estimate_not_the_raw_reading() -> None:
    """An outlier reading (40 m/s while 12 is held) moves the filtered controller's command by at most one step's
    change, computed from the filter's estimate; the previous law followed the raw reading to about 40 m/s."""
    from gaia_app.tasks.drive import SpeedFilter, SpeedKeeper, speed_command

    keepers = {name: SpeedKeeper(12.0, 0.5, 0.48, name, SpeedFilter(0.3, 2.5)) for name in ("filtered", "previous")}
    for keeper in keepers.values():
        keeper.start(12.0)
        for _ in range(20):
            keeper.next(12.0)
    filtered = keepers["filtered"]
    command, estimate = filtered.command, filtered.next(40.0)
    assert 12.0 < estimate < 12.0 + 0.25 * 28  # a settled gain takes a small share of the outlier
    assert filtered.command == speed_command(command, estimate, 12.0, 0.5, 0.48)
    assert abs(filtered.command - 12) <= 0.48 + 1e-9
    keepers["previous"].next(40.0)
    assert keepers["previous"].command == pytest.approx(40.0 - 0.48)
    assert speed_command(8.0, 12.0, 12.0, 0.5, 1.0) == 8.0  # on target: the command keeps what it has
    assert speed_command(8.0, 10.0, 12.0, 0.5, 2.0) == 9.0 and speed_command(8.0, 4.0, 12.0, 0.5, 1.0) == 9.0
    assert speed_command(0.5, 20.0, 0.0, 1.0, 2.0) == 0.0  # never a negative speed
    open_loop = SpeedKeeper(12.0, 0.5, 0.48, "open-loop")
    open_loop.start(6.0)
    for reading, command in ((0.0, 6.48), (50.0, 6.96)):  # a ramp to the target: the readings play no part
        open_loop.next(reading)
        assert open_loop.command == pytest.approx(command)
    with pytest.raises(ValueError, match="controller='pid'"):
        SpeedKeeper(12.0, 0.5, 0.48, "pid")


def test_the_trajectory() -> None:
    from gaia_app.tasks.drive import pose_step

    pose = np.zeros(3)
    for _ in range(100):  # one full circle of radius 20 m at 10 m/s
        pose = pose_step(pose, 10.0, 1 / 20, 2 * np.pi * 20 / 10 / 100)
    np.testing.assert_allclose(pose[:2], [0.0, 0.0], atol=1e-9)
    assert pose[2] == pytest.approx(2 * np.pi)
    np.testing.assert_allclose(pose_step(np.zeros(3), 10.0, 0.0, 0.5), [5.0, 0.0, 0.0])


def test_closed_loop_drive_writes_its_recording_and_record(tmp_path) -> None:
    import json

    from rerun.chunk import RrdReader

    from gaia_app.tasks.drive import main

    results = main(["--seconds", "1", "--out", str(tmp_path), "--target-speed", "10"])
    record = json.loads((tmp_path / "drive.json").read_text())
    assert len(record["steps"]) == len(results["steps"]) == 7 and record["target_speed"] == 10.0
    assert record["controller"] == "filtered" and np.isfinite(record["probed_speed_error"])
    assert all(0 <= s["command"][0] <= 70 and np.isfinite(s["estimated_speed"]) and np.isfinite(s["probed_speed"])
               for s in record["steps"])
    entities = {c.entity_path for c in RrdReader(str(tmp_path / "drive.rrd")).stream().collect().stream().to_chunks()}
    assert {"/camera", "/speed/commanded", "/speed/probed", "/speed/estimated", "/trajectory"} <= entities


def test_the_seed_evaluation_pairs_every_controller(tmp_path) -> None:
    """--seeds: every controller on every seed (short episodes here), the mean over seeds and the ratio to the
    held speed's error with bootstrap intervals, in drive_seeds.json."""
    import json

    from gaia_app.tasks.drive import CONTROLLERS, main, parse_seeds

    assert parse_seeds("101-103,7") == [101, 102, 103, 7]
    for bad in ("a-b", "3,3", "-1", ""):
        with pytest.raises(ValueError, match="--seeds="):
            parse_seeds(bad)
    main(["--seconds", "0.5", "--seeds", "1-2", "--guidance", "0", "--out", str(tmp_path)])
    result = json.loads((tmp_path / "drive_seeds.json").read_text())
    assert result["seeds"] == [1, 2] and set(result["summary"]) == set(CONTROLLERS)
    assert result["settings"]["guidance"] == 0 and result["clips"] == [0]
    none = result["summary"]["none"]
    assert none["ratio_to_none"]["mean"] == 1.0 and none["probed_speed_error"]["n"] == 2
    assert none["command_error"]["mean"] > 0 and all(len(v) == 2 for v in result["per_seed"].values())
    for bad in (["--gain", "1.5"], ["--guidance", "-1"], ["--guidance", "nan"], ["--clip", "-1"], ["--seconds", "0"],
                ["--target-speed", "80"],
                ["--seeds", "1", "--controllers", "filtered"], ["--seeds", "1", "--controllers", "fast,none"],
                ["--seeds", "1", "--clips", "x"], ["--clips", "0-3"]):
        with pytest.raises(SystemExit):
            main(bad)


def test_the_seed_evaluation_starts_each_seed_from_its_clip(tmp_path) -> None:
    """--clips: the k-th seed's episodes start from the k-th clip of world --world-seed; --controllers picks the
    compared controllers (the baseline "none" kept)."""
    import json

    from gaia_app.tasks.drive import main

    main(["--seconds", "0.3", "--seeds", "4-6", "--clips", "2-3", "--world-seed", "77", "--controllers",
          "filtered,none", "--guidance", "0", "--out", str(tmp_path)])
    result = json.loads((tmp_path / "drive_seeds.json").read_text())
    assert set(result["summary"]) == {"filtered", "none"} and result["clips"] == [2, 3]
    contexts = [e["context"] for e in result["per_seed"]["filtered"]]
    assert contexts == [{"world_seed": 77, "index": i} for i in (2, 3, 2)] == [e["context"] for e in
                                                                               result["per_seed"]["none"]]


@pytest.mark.slow
def test_the_filtered_controller_halves_the_speed_error_on_seeds_it_was_not_tuned_on(tmp_path, monkeypatch) -> None:
    """The closed-loop claim (docs/simulator.md, "Measured on seeds chosen beforehand": over seeds 201–216 the
    filtered controller's last-5-s speed error is 0.34 [0.30, 0.38] of the uncontrolled one, target ≤ 0.5), pinned
    on the first two of those seeds with the documented command and defaults (guidance ×1.5), one thread as
    documented: an episode's commands follow the probe's readings, so the thread count's rounding changes single
    episodes (seed 201 with two threads: filtered 2.91 m/s). Measured: filtered 2.00 + 1.46 m/s, none 4.67 + 5.84
    (0.33); unguided (--guidance 0) 2.20 + 2.05 and 4.00 + 3.25 (0.59)."""
    import json

    from gaia_app.tasks.drive import main

    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # what the documented command sets; main's thread policy reads it
    main(["--weights", "gaia1", "--seconds", "10", "--target-speed", "12", "--seeds", "201-202", "--controllers",
          "filtered,none", "--out", str(tmp_path)])
    summary = json.loads((tmp_path / "drive_seeds.json").read_text())["summary"]
    ratio = summary["filtered"]["ratio_to_none"]["mean"]
    assert ratio <= 0.5, summary


def test_the_drive_guides_its_actions_at_the_scale_given(monkeypatch) -> None:
    """--guidance s reaches every episode's reset (GAIA-1 §5.1 guidance on the actions); 0 is unguided, and the two
    give different pictures from one sampler seed."""
    from gaia_app.pipelines.simulator import DrivingSimulator
    from gaia_app.tasks.drive import drive, episode_options, load_world, make_keeper, parse_args

    pipeline, probe = load_world("gaia1")
    env = DrivingSimulator(pipeline, max_steps=2)
    args = parse_args([])
    assert args.guidance == 1.5
    resets: list = []
    original = env.reset
    monkeypatch.setattr(env, "reset", lambda **kw: resets.append(kw.get("options")) or original(**kw))
    readings = {scale: [s["probed_speed"] for s in drive(env, probe, None, 2, make_keeper(args, pipeline.rate), 0.0,
                                                         seed=3, progress=False,
                                                         options=episode_options(args) | {"guidance": scale})["steps"]]
                for scale in (0.0, 1.5)}
    assert [r["guidance"] for r in resets] == [0.0, 1.5] and env.guidance.scale == 1.5
    assert resets[0]["world_seed"] == 1000 and resets[0]["index"] == 0
    assert readings[0.0] != readings[1.5]


def test_closed_loop_drive_captures_its_live_view(tmp_path, monkeypatch) -> None:
    """--screenshot streams the episode live to a headless viewer and writes what it shows (issue 25, item 6); the
    viewer binary (a child of the `rerun` launcher) is stopped afterwards, not left running."""
    import cv2

    from gaia_app.tasks import drive
    from gaia_app.viz.screenshot import ViewerUnavailable, spawn_headless

    spawned = []
    monkeypatch.setattr(drive, "spawn_headless", lambda: spawned.append(spawn_headless()) or spawned[-1])
    try:
        drive.main(["--seconds", "0.5", "--out", str(tmp_path), "--screenshot", str(tmp_path / "live.png")])
    except ViewerUnavailable as why:
        pytest.skip(f"headless Rerun viewer unavailable here: {why}")
    shot = cv2.imread(str(tmp_path / "live.png"))
    assert max(shot.shape[:2]) == 1280
    assert shot.std() > 20 and len(np.unique(shot.reshape(-1, 3), axis=0)) > 1000  # the camera view is painted
    group = spawned[0][1].pid  # the viewer's process group: the launcher and the binary
    alive = [p for p in Path("/proc").iterdir() if p.name.isdigit() and _running_in(p, group)]
    assert not alive, f"viewer processes left running: {[p.name for p in alive]}"


def _running_in(proc: Path, group: int) -> bool:
    """Whether /proc/<pid> is a live (not zombie) process of the process group `group`."""
    try:
        state, _, pgrp = (proc / "stat").read_text().rsplit(")", 1)[1].split()[:3]
        return int(pgrp) == group and state != "Z"
    except (OSError, ValueError):
        return False


def test_a_program_that_is_not_a_rerun_viewer_on_the_port_is_not_sent_the_episode(tmp_path, capsys) -> None:
    """A web server on --viewer-port: the drive says so and records to drive.rrd only (it used to stream the episode
    there and crash before writing drive.json)."""
    import argparse
    import http.server
    import threading

    from gaia_app.tasks.drive import open_recording
    from gaia_app.viz.viewer import speaks_grpc

    server = http.server.HTTPServer(("127.0.0.1", 0), http.server.BaseHTTPRequestHandler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        port = server.server_address[1]
        assert not speaks_grpc("127.0.0.1", port)
        args = argparse.Namespace(seed=0, out=tmp_path, screenshot=None, viewer=True, viewer_port=port)
        rec, headless = open_recording(args)
        rec.flush()
        assert headless is None
        assert f"--viewer-port {port} is taken by a program that is not a Rerun viewer" in capsys.readouterr().out
    finally:
        server.shutdown()
