r"""Context prediction of a trained GAIA-2 latent world model on held-out latent-cache windows.

    python benchmarks/eval_latent_world_model.py --world-model-ckpt WM/checkpoints/last.ckpt \
        --tokenizer-ckpt TOK/checkpoints/last.ckpt --latents data/latents/val
    python benchmarks/eval_latent_world_model.py --weights gaia2 --latents data/latents/val   # a weights folder

For each window of `--steps` latent steps: the first `--context` steps are given clean, the rest are
generated (LatentWorldModelPipeline.rollout, one chunk, the window's own conditions, Euler 50 linear-quadratic
steps). Reports the latent MSE and the PSNR of the decoded frames against the tokenizer's decoding of the real
latents, next to two baselines: repeating the last context step, and each channel's mean over the context
("mean latent", a static blur). A sample is one plausible future, not the average one, so a good model need
not beat "repeat" on MSE; it should beat "mean latent" and stay close to "repeat" in PSNR while moving.
`--samples K` (K > 1) adds the latent mean of K samples of each window: a point forecast, the estimate PSNR rewards,
which a model that predicts the motion should bring above "repeat". Every row carries ± 95 % over windows and its
paired PSNR difference to "repeat".
"""

from __future__ import annotations

import argparse

import torch
from tqdm import tqdm

from gaia_app.data.latent_cache import find_latent_clips, read_latent_clip
from gaia_app.data.latent_windows import LatentWindows, collate_latent_windows
from gaia_app.data.metadata import MetadataEncoder
from gaia_app.diffusion.flow_matching import FlowSampler
from gaia_app.eval.metrics import psnr
from gaia_app.models.gaia2.conditioning import batch_conditions
from gaia_app.pipelines.gaia2 import Gaia2Pipeline


def decoded_psnr(tokenizer, latents: torch.Tensor, reference: torch.Tensor) -> float:
    """PSNR (dB) of decode(latents) against decode(reference latents), both (b, v, t, C, h, w)."""
    a = tokenizer.decode(latents).clamp(-1, 1).flatten(0, 2)
    b = tokenizer.decode(reference).clamp(-1, 1).flatten(0, 2)
    return float(psnr(a, b).mean())


@torch.no_grad()
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--world-model-ckpt", help="a latent world model training checkpoint (with --tokenizer-ckpt)")
    parser.add_argument("--tokenizer-ckpt", help="the video tokenizer checkpoint its latents come from")
    parser.add_argument("--weights", help="instead of the two checkpoints: a weights folder (e.g. gaia2)")
    parser.add_argument("--latents", required=True, help="a split folder of a latent cache (e.g. data/latents/val)")
    parser.add_argument("--steps", type=int, default=4)
    parser.add_argument("--context", type=int, default=2)
    parser.add_argument("--solver-steps", type=int, default=50)
    parser.add_argument("--samples", type=int, default=1, help="samples per window; > 1 adds their mean as a row")
    args = parser.parse_args()
    if args.samples < 1:
        parser.error(f"--samples {args.samples}: expected at least 1")
    if bool(args.weights) == bool(args.world_model_ckpt and args.tokenizer_ckpt):
        parser.error("give --weights, or --world-model-ckpt and --tokenizer-ckpt")
    torch.manual_seed(0)
    folders = find_latent_clips(args.latents)
    sampler = FlowSampler(steps=args.solver_steps)
    if args.weights:
        models = Gaia2Pipeline.from_weights(args.weights, sampler)
    else:
        height, width = read_latent_clip(folders[0]).image_size
        models = Gaia2Pipeline.from_checkpoints(args.tokenizer_ckpt, args.world_model_ckpt, height, width, sampler)
    pipe, tokenizer, scale, c = models.world, models.tokenizer, models.scale, args.context
    fields = list(pipe.model.conditioner.metadata_fields)
    windows = LatentWindows(folders, args.steps, MetadataEncoder(fields), random_window=False)
    mean_row = f"world model, mean of {args.samples} samples"
    names = ["world model"] + ([mean_row] if args.samples > 1 else []) + ["repeat last context step", "mean latent"]
    rows: dict[str, list[float]] = {name: [] for name in names}
    mses: dict[str, list[float]] = {name: [] for name in names}
    for i in tqdm(range(len(windows)), desc="windows"):
        batch = collate_latent_windows([windows[i]])
        real = batch["mean"] * scale
        cond = batch_conditions(batch, models.text_vector(batch))
        samples = [pipe.rollout(real[:, :, :c], [cond], chunk_steps=args.steps - c,
                                generator=torch.Generator().manual_seed(i * args.samples + k))
                   for k in range(args.samples)]
        candidates = {"world model": samples[0],
                      **({mean_row: torch.stack(samples).mean(0)} if args.samples > 1 else {}),
                      "repeat last context step": torch.cat([real[:, :, :c]]
                                                            + [real[:, :, c - 1 : c]] * (args.steps - c), 2),
                      "mean latent": torch.cat([real[:, :, :c], real[:, :, :c].mean(dim=(2, 4, 5), keepdim=True)
                                                .expand(-1, -1, args.steps - c, -1, *real.shape[-2:])], 2)}
        for name, latents in candidates.items():
            future = slice(c, args.steps)
            mses[name].append(float((latents[:, :, future] - real[:, :, future]).pow(2).mean()))
            rows[name].append(decoded_psnr(tokenizer, latents[:, :, future] / scale, real[:, :, future] / scale))
    print(f"{len(windows)} windows, {c} context + {args.steps - c} generated latent steps, "
          f"{args.solver_steps} Euler steps")
    print("| prediction | latent MSE | decoded PSNR vs decoded real (dB) | PSNR − repeat (dB) |")
    print("|---|---:|---:|---:|")
    repeat = torch.tensor(rows["repeat last context step"])
    for name, values in rows.items():
        psnrs = torch.tensor(values)
        print(f"| {name} | {sum(mses[name]) / len(mses[name]):.3f} | {interval(psnrs)} | {interval(psnrs - repeat)} |")


def interval(values: torch.Tensor) -> str:
    """mean ± 95 % normal interval over windows."""
    half = 1.96 * float(values.std()) / len(values) ** 0.5 if len(values) > 1 else float("nan")
    return f"{float(values.mean()):.2f} ± {half:.2f}"


if __name__ == "__main__":
    main()
