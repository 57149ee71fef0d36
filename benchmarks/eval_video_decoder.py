"""Evaluate and diagnose a trained GAIA-1 video decoder on held-out synthetic clips (issues 6, 21; GAIA-1 §2.4, §5.2).

    python train.py experiment=gaia1/reference/video_decoder hydra.run.dir=outputs/reference/video_decoder
    python benchmarks/eval_video_decoder.py --ckpt outputs/reference/video_decoder/checkpoints/last.ckpt
    python benchmarks/eval_video_decoder.py --weights gaia1 --world-seed 31337 --clips 16 --rows-only \
        --samplers mean16,amean8 --out outputs/decoder_draws      # the shipped decoder (float16 weights)

Decodes the ground-truth tokens of held-out clips (N frames at 6.25 Hz, the validation seed) side by side:
  framewise   the tokenizer's own image decoder, one frame at a time: the rendered tokens alone, what the video
              decoder replaces and, for a residual decoder, its input
  ddim<k>     the §5.2 procedure (backward AR windows of T' = 7 with 2 context frames), EMA weights, k DDIM steps
              (default 1, 5, 10, 20, 50; DDIM 1 is the decoder's one-step x̂₀ from pure noise)
  zero        the one-step x̂₀ from x_T = 0 instead of noise (an input the decoder never saw in training)
  mean<k>     the conditional-mean estimate: one-step x̂₀ averaged over k noise draws (OneStepMeanSampler)
  amean<k>    the same over k/2 antithetic pairs of draws (x_T, −x_T), if asked
  dpm<k>      DPM-Solver++(2M) with k steps, if asked (--samplers)
  sddim<k>    DDIM with k steps from one initial noise shared by the frames of each window (a diagnosis of where
              flicker comes from, if asked; the decoder was trained with independent noise per frame)
and reports, per row, PSNR against the true frames and temporal flicker (mean |Δdecoded − Δtrue| of consecutive
frames, gaia_app.eval.metrics.temporal_flicker; lower is steadier), each a mean over clips with a 95 % interval,
and the paired difference to framewise with its interval. Then the temporal upsampling 6.25 → 12.5 → 25 Hz against
the true 25 Hz frames, and the 25 Hz decoding path's frames/s at the tiny (trained) and a mid size (random weights,
same cost; --rows-only skips these two). Writes results.json, results.md, steps.png (PSNR and flicker against
steps), a PNG strip (true | framewise | decoder) and an .rrd into --out.
"""

from __future__ import annotations

import argparse
import copy
import json
import time
from functools import partial
from pathlib import Path

import numpy as np
import rerun as rr
import torch
from einops import rearrange
from omegaconf import OmegaConf

import gaia_app.utils.resolvers  # noqa: F401
from gaia_app.data.synthetic import SyntheticClipDataset
from gaia_app.diffusion.samplers import DDIMSampler, DPMSolverSampler, OneStepMeanSampler
from gaia_app.eval.metrics import psnr, temporal_flicker
from gaia_app.lit.checkpoint import load_module
from gaia_app.lit.gaia1_video_decoder import VideoDecoderModule
from gaia_app.models.gaia1.video_decoder import VideoDecoder
from gaia_app.pipelines.gaia1_video_decoder import VideoDecodingPipeline
from gaia_app.utils.run_dir import atomic_path, atomic_write_text
from gaia_app.viz.media import to_hwc_uint8

# rows: ddim<k> (k DDIM steps), dpm<k> (DPM-Solver++ k steps), mean<k> (OneStepMeanSampler, k noise draws),
# amean<k> (k/2 antithetic pairs), zero (x̂0 from x_T = 0, one evaluation), sddim<k> (StartedDDIM)
SAMPLERS = {"ddim": DDIMSampler, "dpm": DPMSolverSampler, "mean": OneStepMeanSampler,
            "amean": partial(OneStepMeanSampler, antithetic=True)}
DEFAULT_SAMPLERS = "ddim1,ddim5,ddim10,ddim20,ddim50,zero,mean4,mean16"


class ShippedDecoder:
    """What this benchmark reads of a VideoDecoderModule (EMA decoder, schedule, window, tokenize, render_tokens),
    from a shipped weights folder (--weights): the decoder and tokenizer exactly as they ship."""

    def __init__(self, folder: str, device: str):
        from gaia_app.diffusion.noise_schedule import CosineNoiseSchedule
        from gaia_app.weights.folders import load_nets, shipped_folder

        folder = shipped_folder(folder)
        tokenizer, tokenizer_info = load_nets(folder, "tokenizer", device)
        decoder, info = load_nets(folder, "video_decoder", device)
        self.tokenizer, self.ema_decoder = tokenizer["net"], decoder["net"]
        self.schedule = CosineNoiseSchedule(int(info["timesteps"]))
        self.frames, self.context_frames = int(info["frames"]), int(info["context_frames"])
        self.image_size = tuple(tokenizer_info["image_size"])

    # VideoDecoderModule's own methods: they read nothing but `self.tokenizer`
    tokenize = VideoDecoderModule.tokenize
    render_tokens = VideoDecoderModule.render_tokens

    def data_config(self, world_seed: int):
        """The held-out clips' source: the synthetic world `world_seed` at the tokenizer's image size, one camera."""
        height, width = self.image_size
        return OmegaConf.create({"data": {"val_source": {"seed": world_seed, "height": height, "width": width,
                                                          "cameras": ["front"]}}})


def held_out_clips(run_cfg, clips: int, frames: int, seed: int | None = None) -> torch.Tensor:
    """(clips, 4·(frames − 1) + 1, 3, H, W) in [-1, 1]: synthetic clips at 25 Hz from the validation seed, or from
    `seed` (a world neither training nor any choice made on the validation clips has seen)."""
    src = run_cfg.data.val_source
    ds = SyntheticClipDataset(num_clips=clips, seed=int(src.seed if seed is None else seed), height=int(src.height),
                              width=int(src.width), cameras=list(src.cameras), clip_len=4 * (frames - 1) + 1,
                              fps=25.0)
    video = torch.stack([torch.from_numpy(ds[i].frames[0]) for i in range(clips)])  # (clips, t, 3, H, W) uint8
    return video.float() / 127.5 - 1


def per_clip(video: torch.Tensor, truth: torch.Tensor) -> dict[str, torch.Tensor]:
    """{"psnr": (b,) mean PSNR of each clip's frames, "flicker": (b,)} for videos (b, t, 3, H, W)."""
    b = video.shape[0]
    frame_psnr = psnr(rearrange(video, "b t c h w -> (b t) c h w"), rearrange(truth, "b t c h w -> (b t) c h w"))
    return {"psnr": frame_psnr.reshape(b, -1).mean(1), "flicker": temporal_flicker(video, truth)}


def interval(values: torch.Tensor) -> dict[str, float]:
    """Mean and 95 % normal interval half-width over clips (values: (b,))."""
    half = 1.96 * float(values.std()) / len(values) ** 0.5 if len(values) > 1 else float("nan")
    return {"mean": float(values.mean()), "ci95": half}


def scores(video: torch.Tensor, truth: torch.Tensor, baseline: dict[str, torch.Tensor] | None = None) -> dict:
    """Mean ± 95 % interval of PSNR and flicker over clips; with `baseline` (per_clip of framewise) also the
    paired differences video − baseline."""
    clips = per_clip(video, truth)
    out = {name: interval(values) for name, values in clips.items()}
    if baseline is not None:
        out.update({f"{name}_minus_framewise": interval(clips[name] - baseline[name]) for name in clips})
    return out


def table(results: dict) -> str:
    """results.md: one row per decoding, PSNR and flicker with intervals and paired differences to framewise."""
    def cell(entry: dict, digits: int) -> str:
        return f"{entry['mean']:.{digits}f} ± {entry['ci95']:.{digits}f}"
    lines = [f"{results['clips']} held-out clips × {results['frames_6_25hz']} frames at 6.25 Hz, 95 % intervals over "
             "clips; differences are paired (same clips) against framewise.", "",
             "| decoding of the same ground-truth tokens | PSNR (dB) ↑ | flicker ↓ | PSNR − framewise | "
             "flicker − framewise | seconds |", "|---|---|---|---|---|---|"]
    fw = results["framewise_tokenizer"]
    lines.append(f"| tokenizer's image decoder, frame by frame (the rendered tokens) | {cell(fw['psnr'], 2)} | "
                 f"{cell(fw['flicker'], 4)} | | | < 1 |")
    for name, row in results["samplers"].items():
        lines.append(f"| {name} | {cell(row['psnr'], 2)} | {cell(row['flicker'], 4)} | "
                     f"{cell(row['psnr_minus_framewise'], 2)} | {cell(row['flicker_minus_framewise'], 4)} | "
                     f"{row['seconds']:.0f} |")
    return "\n".join(lines) + "\n"


def plot_steps(path: Path, results: dict) -> None:
    """steps.png: PSNR and flicker of the DDIM rows against steps, framewise as a line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = {int(k[4:]): v for k, v in results["samplers"].items() if k.startswith("ddim") and k[4:].isdigit()}
    if not rows:
        return
    steps = sorted(rows)
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2))
    for ax, metric, label in ((axes[0], "psnr", "PSNR (dB) ↑"), (axes[1], "flicker", "flicker ↓")):
        ax.errorbar(steps, [rows[k][metric]["mean"] for k in steps], yerr=[rows[k][metric]["ci95"] for k in steps],
                    marker="o", capsize=3, label="video decoder, DDIM")
        fw = results["framewise_tokenizer"][metric]
        ax.axhline(fw["mean"], color="k", linestyle="--", label="frame by frame (rendered tokens)")
        for name, style in (("mean16", ":"), ("mean4", "-.")):
            if name in results["samplers"]:
                ax.axhline(results["samplers"][name][metric]["mean"], color="g", linestyle=style,
                           label=f"conditional mean, {name[4:]} draws")
        ax.set_xscale("log")
        ax.set_xlabel("DDIM steps")
        ax.set_ylabel(label)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    plt.close(fig)


class StartedDDIM:  # the "zero" and "sddim<k>" rows
    """DDIM with k steps from an x_T made from the drawn noise (b, t, ...) by `start`: zeros (the deterministic
    one-step x̂₀, the conditional mean) or the first frame's noise repeated over the window's frames."""

    def __init__(self, schedule, steps: int, start):
        self.inner, self.start, self.clip_x0 = DDIMSampler(schedule, steps=steps), start, True

    def __call__(self, denoise, noise, generator=None, callback=None):
        inner = copy.copy(self.inner)
        inner.clip_x0 = self.clip_x0  # sample_window moves the clip into the denoiser for a residual decoder
        return inner(denoise, self.start(noise), generator=generator, callback=callback)


def zero_start(noise: torch.Tensor) -> torch.Tensor:
    return torch.zeros_like(noise)


def shared_start(noise: torch.Tensor) -> torch.Tensor:
    return noise[:, :1].expand_as(noise).contiguous()


def frames_per_second(pipe: VideoDecodingPipeline, tokens: torch.Tensor) -> float:
    """25 Hz output frames per second of the whole §5.2 path (decode + two doublings) for tokens (b, N, h, w)."""
    pipe(tokens[:, :pipe.frames], upsample=0, generator=torch.Generator().manual_seed(0))  # warm-up
    synchronize(tokens.device)
    start = time.perf_counter()
    video = pipe(tokens, upsample=2, generator=torch.Generator().manual_seed(0))
    synchronize(tokens.device)
    return video.quadruple.shape[0] * video.quadruple.shape[1] / (time.perf_counter() - start)


def denoiser_steps_per_second(net: VideoDecoder, frames: int, repeats: int = 3) -> float:
    """Forward passes per second on one T'-frame window (batch 1), the unit a sampler step costs."""
    h, w = net.token_grid
    height, width = net.image_size
    device = next(net.parameters()).device
    x = torch.randn(1, frames, 3, height, width, device=device)
    args = (torch.full((1,), 500, device=device), torch.zeros(1, frames, h, w, dtype=torch.long, device=device),
            torch.ones(1, frames, dtype=torch.bool, device=device), torch.zeros_like(x),
            torch.zeros(1, frames, dtype=torch.bool, device=device))
    rendered = torch.zeros_like(x) if net.render_tokens else None
    with torch.no_grad():
        net(x, *args, rendered=rendered)
        synchronize(device)
        start = time.perf_counter()
        for _ in range(repeats):
            net(x, *args, rendered=rendered)
        synchronize(device)
    return repeats / (time.perf_counter() - start)


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def write_strip(path: Path, rows: list[torch.Tensor]) -> None:
    """PNG of the first clip: one row per video (b, t, 3, H, W)."""
    import cv2

    strip = np.concatenate([np.concatenate([to_hwc_uint8(frame) for frame in video[0]], axis=1) for video in rows])
    ok, png = cv2.imencode(".png", cv2.cvtColor(strip, cv2.COLOR_RGB2BGR))
    with atomic_path(path) as tmp:
        tmp.write_bytes(png.tobytes())


def sampler_for(name: str, schedule):
    """A row name of SAMPLERS (ddim50, mean16, zero, …) → its sampler."""
    if name == "zero":
        return StartedDDIM(schedule, 1, zero_start)
    kind, count = name.rstrip("0123456789"), name[len(name.rstrip("0123456789")):]
    if kind == "sddim" and count:
        return StartedDDIM(schedule, int(count), shared_start)
    if kind not in SAMPLERS or not count:
        raise ValueError(f"--samplers: unknown row {name!r}; expected ddim<k>, sddim<k>, dpm<k>, mean<k>, amean<k> "
                         "or zero")
    if kind.endswith("mean"):
        return SAMPLERS[kind](schedule, draws=int(count))
    return SAMPLERS[kind](schedule, steps=int(count))


def upsampling_scores(module, tokens: torch.Tensor, full: torch.Tensor, sampler: str, seed: int) -> dict:
    """PSNR (all 25 Hz frames, interpolated ones only) and flicker of the 6.25 → 12.5 → 25 Hz path against the true
    25 Hz clips `full` (b, 4·(N − 1) + 1, 3, H, W), decoding the tokens (b, N, h, w) with the row `sampler`."""
    net, schedule = module.ema_decoder, module.schedule
    pipe = VideoDecodingPipeline(net, schedule, sampler_for(sampler, schedule), module.frames, module.context_frames,
                                 render_tokens=module.render_tokens)
    up = pipe(tokens, upsample=2, generator=torch.Generator().manual_seed(seed))
    quadruple = up.quadruple.cpu()
    inserted = torch.ones(quadruple.shape[1], dtype=torch.bool)
    inserted[::4] = False
    return {"sampler": sampler, "frames": [up.base.shape[1], up.double.shape[1], quadruple.shape[1]],
            "psnr_25hz_all": scores(quadruple, full)["psnr"],
            "psnr_25hz_interpolated_only": scores(quadruple[:, inserted], full[:, inserted])["psnr"],
            "flicker_25hz": scores(quadruple, full)["flicker"]}


def speed_section(module, one_clip: torch.Tensor, sampler: str, device: str) -> dict:
    """Denoiser steps/s and 25 Hz frames/s of the trained decoder and of a mid-size one (random weights, same cost)."""
    net, schedule = module.ema_decoder, module.schedule
    mid = VideoDecoder(vocab_size=net.vocab_size, token_grid=net.token_grid, image_size=net.image_size,
                       frames=module.frames, channels=64, channel_mults=(1, 2, 4), res_blocks=2, attention_levels=(2,),
                       render_tokens=net.render_tokens, residual=net.residual,
                       residual_scale=net.residual_scale).to(device).eval()
    return {
        "tiny_params": sum(p.numel() for p in net.parameters()),
        "mid_params": sum(p.numel() for p in mid.parameters()),
        "denoiser_steps_per_s": {"tiny": denoiser_steps_per_second(net, module.frames),
                                 "mid": denoiser_steps_per_second(mid, module.frames)},
        "frames_25hz_per_s": {size: frames_per_second(VideoDecodingPipeline(
            model, schedule, sampler_for(sampler, schedule), module.frames, module.context_frames,
            render_tokens=module.render_tokens), one_clip) for size, model in (("tiny", net), ("mid", mid))},
        "threads": torch.get_num_threads(),
        "device": str(device),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--ckpt", help="a video decoder training checkpoint (EMA weights)")
    source.add_argument("--weights", help="a shipped weights folder (gaia1 or a path; needs --world-seed, --out)")
    parser.add_argument("--clips", type=int, default=8)
    parser.add_argument("--frames", type=int, default=12, help="N frames at 6.25 Hz (12: two decoder windows)")
    parser.add_argument("--out", default=None, help="default: <run dir>/eval")
    parser.add_argument("--samplers", default=DEFAULT_SAMPLERS, help=f"comma-separated, of {','.join(SAMPLERS)}")
    parser.add_argument("--upsample-sampler", default="mean16", help="row name of the sampler of the 25 Hz path")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="cpu", help="cpu or cuda (frames/s on a GPU)")
    parser.add_argument("--world-seed", type=int, default=None,
                        help="clips of this world instead of the validation one")
    parser.add_argument("--rows-only", action="store_true", help="skip the 25 Hz upsampling and the speed section")
    args = parser.parse_args()
    if args.weights and (args.world_seed is None or args.out is None):
        parser.error("--weights needs --world-seed (shipped weights carry no validation world) and --out")
    torch.manual_seed(args.seed)
    if args.weights:
        module = ShippedDecoder(args.weights, args.device)
        out, run_cfg = Path(args.out), module.data_config(args.world_seed)
    else:
        module = load_module(args.ckpt).eval().to(args.device)
        run_dir = Path(args.ckpt).parents[1]
        out = Path(args.out or run_dir / "eval")
        run_cfg = OmegaConf.load(run_dir / "config_resolved.yaml")
    net, schedule = module.ema_decoder.eval(), module.schedule

    full = held_out_clips(run_cfg, args.clips, args.frames, args.world_seed)  # 25 Hz, on the CPU (metrics there)
    truth = full[:, ::4]  # 6.25 Hz, N frames
    tokens = module.tokenize(truth.to(args.device))
    framewise = module.render_tokens(tokens).cpu()
    baseline = per_clip(framewise, truth)
    results = {"clips": args.clips, "frames_6_25hz": args.frames, "world_seed": args.world_seed,
               "framewise_tokenizer": scores(framewise, truth), "samplers": {}}
    decoded = {}
    for name in args.samplers.split(","):
        pipe = VideoDecodingPipeline(net, schedule, sampler_for(name, schedule), module.frames, module.context_frames,
                                     render_tokens=module.render_tokens)
        start = time.perf_counter()
        decoded[name] = pipe.decode(tokens, torch.Generator().manual_seed(args.seed)).cpu()
        results["samplers"][name] = {**scores(decoded[name], truth, baseline), "seconds": time.perf_counter() - start}
        print(name, json.dumps(results["samplers"][name]), flush=True)
    best = decoded.get("ddim50", next(iter(decoded.values())))
    if not args.rows_only:
        results["upsampling"] = upsampling_scores(module, tokens, full, args.upsample_sampler, args.seed)
        results["speed"] = speed_section(module, tokens[:1], args.upsample_sampler, args.device)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "results.json", json.dumps(results, indent=2))
    atomic_write_text(out / "results.md", table(results))
    plot_steps(out / "steps.png", results)
    write_strip(out / "decoder_strip.png", [truth, framewise, best])
    rec = rr.RecordingStream("gaia_app_eval_video_decoder")
    rec.save(str(out / "eval.rrd"))
    for name, video in (("truth", truth), ("framewise", framewise), *decoded.items()):
        for t in range(video.shape[1]):
            rec.set_time("frame", sequence=t)
            rec.log(f"eval/{name}", rr.Image(to_hwc_uint8(video[0, t])))
    rec.flush()
    print(table(results))
    if not args.rows_only:
        print(json.dumps(results["upsampling"], indent=2), json.dumps(results["speed"], indent=2))


if __name__ == "__main__":
    main()
