"""Evaluate a trained GAIA-1 video decoder on held-out synthetic clips (issue 6, GAIA-1 §2.4, §5.2).

    python train.py experiment=gaia1/video_decoder_tiny hydra.run.dir=outputs/video_decoder
    python benchmarks/eval_video_decoder.py --ckpt outputs/video_decoder/checkpoints/last.ckpt

Decodes the ground-truth tokens of held-out clips (N frames at 6.25 Hz) two ways, side by side:
  decoder     the §5.2 procedure (backward AR windows of T' = 7 with 2 context frames), EMA weights
  framewise   the tokenizer's own image decoder, one frame at a time (what the video decoder replaces)
and reports PSNR against the true frames and temporal flicker (mean |Δdecoded − Δtrue| of consecutive
frames, gaia_app.eval.metrics.temporal_flicker; lower is steadier). Then the samplers side by side
(DDIM 50/20/10, DPM-Solver++ 20/10: PSNR, flicker, seconds), the temporal upsampling 6.25 → 12.5 → 25 Hz
against the true 25 Hz frames, and denoiser forward steps/s at the tiny size and a mid size.
Writes results.json, a PNG strip (true | framewise | decoder) and an .rrd into --out.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import rerun as rr
import torch
from einops import rearrange
from hydra.utils import instantiate
from omegaconf import OmegaConf

import gaia_app.utils.resolvers  # noqa: F401
from gaia_app.data.synthetic import SyntheticClipDataset
from gaia_app.diffusion.samplers import DDIMSampler, DPMSolverSampler
from gaia_app.eval.metrics import psnr, temporal_flicker
from gaia_app.lit.checkpoint import load_module
from gaia_app.models.gaia1.video_decoder import VideoDecoder
from gaia_app.pipelines.gaia1_video_decoder import VideoDecodingPipeline
from gaia_app.utils.run_dir import atomic_path, atomic_write_text
from gaia_app.viz.media import to_hwc_uint8

SAMPLERS = {"ddim50": (DDIMSampler, 50), "ddim20": (DDIMSampler, 20), "ddim10": (DDIMSampler, 10),
            "dpm20": (DPMSolverSampler, 20), "dpm10": (DPMSolverSampler, 10)}


def held_out_clips(run_cfg, clips: int, frames: int) -> torch.Tensor:
    """(clips, 4·(frames − 1) + 1, 3, H, W) in [-1, 1]: synthetic clips from the validation seed at 25 Hz."""
    src = run_cfg.data.val_source
    ds = SyntheticClipDataset(num_clips=clips, seed=int(src.seed), height=int(src.height), width=int(src.width),
                              cameras=list(src.cameras), clip_len=4 * (frames - 1) + 1, fps=25.0)
    video = torch.stack([torch.from_numpy(ds[i].frames[0]) for i in range(clips)])  # (clips, t, 3, H, W) uint8
    return video.float() / 127.5 - 1


def scores(video: torch.Tensor, truth: torch.Tensor) -> dict[str, float]:
    frames = rearrange(video, "b t c h w -> (b t) c h w")
    return {"psnr": float(psnr(frames, rearrange(truth, "b t c h w -> (b t) c h w")).mean()),
            "flicker": float(temporal_flicker(video, truth).mean())}


def denoiser_steps_per_second(net: VideoDecoder, frames: int, repeats: int = 3) -> float:
    """Forward passes per second on one T'-frame window (batch 1), the unit a sampler step costs."""
    h, w = net.token_grid
    height, width = net.image_size
    x = torch.randn(1, frames, 3, height, width)
    args = (torch.full((1,), 500), torch.zeros(1, frames, h, w, dtype=torch.long), torch.ones(1, frames, dtype=torch.bool),
            torch.zeros_like(x), torch.zeros(1, frames, dtype=torch.bool))
    rendered = torch.zeros_like(x) if net.render_tokens else None
    with torch.no_grad():
        net(x, *args, rendered=rendered)
        start = time.perf_counter()
        for _ in range(repeats):
            net(x, *args, rendered=rendered)
    return repeats / (time.perf_counter() - start)


def write_strip(path: Path, rows: list[torch.Tensor]) -> None:
    """PNG of the first clip: one row per video (b, t, 3, H, W)."""
    import cv2

    strip = np.concatenate([np.concatenate([to_hwc_uint8(frame) for frame in video[0]], axis=1) for video in rows])
    ok, png = cv2.imencode(".png", cv2.cvtColor(strip, cv2.COLOR_RGB2BGR))
    with atomic_path(path) as tmp:
        tmp.write_bytes(png.tobytes())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", required=True)
    parser.add_argument("--clips", type=int, default=4)
    parser.add_argument("--frames", type=int, default=12, help="N frames at 6.25 Hz (12: two decoder windows)")
    parser.add_argument("--out", default=None, help="default: <run dir>/eval")
    parser.add_argument("--samplers", default=",".join(SAMPLERS))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    module = load_module(args.ckpt).eval()
    run_dir = Path(args.ckpt).parents[1]
    out = Path(args.out or run_dir / "eval")
    run_cfg = OmegaConf.load(run_dir / "config_resolved.yaml")
    net, schedule = module.ema_decoder.eval(), module.schedule

    full = held_out_clips(run_cfg, args.clips, args.frames)  # 25 Hz
    truth = full[:, ::4]  # 6.25 Hz, N frames
    tokens = module.tokenize(truth)
    framewise = module.render_tokens(tokens)
    results = {"clips": args.clips, "frames_6_25hz": args.frames, "framewise_tokenizer": scores(framewise, truth), "samplers": {}}
    decoded = {}
    for name in args.samplers.split(","):
        cls, steps = SAMPLERS[name]
        pipe = VideoDecodingPipeline(net, schedule, cls(schedule, steps=steps), module.frames, module.context_frames,
                                    render_tokens=module.render_tokens)
        start = time.perf_counter()
        decoded[name] = pipe.decode(tokens, torch.Generator().manual_seed(args.seed))
        results["samplers"][name] = {**scores(decoded[name], truth), "seconds": time.perf_counter() - start}
        print(name, results["samplers"][name], flush=True)
    best = decoded.get("ddim50", next(iter(decoded.values())))
    pipe = VideoDecodingPipeline(net, schedule, DDIMSampler(schedule, steps=20), module.frames, module.context_frames,
                                render_tokens=module.render_tokens)
    up = pipe(tokens, upsample=2, generator=torch.Generator().manual_seed(args.seed))
    inserted = torch.ones(up.quadruple.shape[1], dtype=torch.bool)
    inserted[::4] = False
    results["upsampling"] = {
        "frames": [up.base.shape[1], up.double.shape[1], up.quadruple.shape[1]],
        "psnr_25hz_all": scores(up.quadruple, full)["psnr"],
        "psnr_25hz_interpolated_only": scores(up.quadruple[:, inserted], full[:, inserted])["psnr"],
        "flicker_25hz": scores(up.quadruple, full)["flicker"],
    }
    mid = VideoDecoder(vocab_size=net.vocab_size, token_grid=net.token_grid, image_size=net.image_size, frames=module.frames,
                       channels=64, channel_mults=(1, 2, 4), res_blocks=2, attention_levels=(2,),
                       render_tokens=net.render_tokens)
    results["denoiser_steps_per_s"] = {
        "tiny": denoiser_steps_per_second(net, module.frames),
        "mid": denoiser_steps_per_second(mid.eval(), module.frames),
        "tiny_params": sum(p.numel() for p in net.parameters()),
        "mid_params": sum(p.numel() for p in mid.parameters()),
    }
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "results.json", json.dumps(results, indent=2))
    write_strip(out / "decoder_strip.png", [truth, framewise, best])
    rec = rr.RecordingStream("gaia_app_eval_video_decoder")
    rec.save(str(out / "eval.rrd"))
    for name, video in (("truth", truth), ("framewise", framewise), ("decoder", best)):
        for t in range(video.shape[1]):
            rec.set_time("frame", sequence=t)
            rec.log(f"eval/{name}", rr.Image(to_hwc_uint8(video[0, t])))
    rec.flush()
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
