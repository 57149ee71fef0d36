"""The pipelines a `generate.py` config names: its shipped `weights` folder or its training checkpoints, with the
sampler, guidance and decoder settings of the config (GAIA-1: `load_pipeline`; GAIA-2: `load_gaia2`)."""

from __future__ import annotations

from hydra.utils import instantiate
from omegaconf import DictConfig

from gaia_app.diffusion.samplers import ImageVideoBlend
from gaia_app.pipelines.gaia1 import Gaia1Pipeline
from gaia_app.pipelines.gaia2 import Gaia2Pipeline
from gaia_app.weights.folders import shipped_folder


def decoder_blend(cfg: DictConfig) -> ImageVideoBlend | None:
    """The eq. 4 image/video blend of `cfg.decoder_blend` (GAIA-1 §5.2), None when its probability is 0."""
    blend = cfg.get("decoder_blend")
    if blend is None or float(blend.probability) == 0:
        return None
    return ImageVideoBlend(float(blend.probability), float(blend.weight))


def load_pipeline(cfg: DictConfig, video_decoder: bool | None = None) -> Gaia1Pipeline:
    """The three checkpoints of `cfg` (decoder optional), or its shipped `weights`, with the sampler and guidance
    of `cfg`. video_decoder: whether `weights` runs decode with the folder's video decoder (None: `cfg.video_decoder`;
    the controllability protocol passes False, as its probes are measured on frames decoded by the tokenizer)."""
    guided = cfg.guidance.scale > 0 or (cfg.guidance.get("text_scale") or 0) > 0
    guidance = instantiate(cfg.guidance) if guided else None
    if cfg.negative_prompt and guidance is None:
        raise ValueError("negative_prompt replaces the unconditioned stream of guidance: set guidance.scale > 0")
    if cfg.get("weights"):
        given = [key for key in ("tokenizer_ckpt", "world_model_ckpt", "decoder_ckpt") if cfg.get(key)]
        if given:
            raise ValueError(f"weights={cfg.weights} replaces the checkpoints; drop {', '.join(given)}")
        use_decoder = bool(cfg.get("video_decoder", True)) if video_decoder is None else video_decoder
        pipeline = Gaia1Pipeline.from_weights(shipped_folder(cfg.weights), device=cfg.device, video_decoder=use_decoder,
                                              decoder_steps=cfg.decoder_steps, decoder_blend=decoder_blend(cfg),
                                              decoder_sampler=cfg.decoder_sampler, upsample=cfg.upsample,
                                              sampler=instantiate(cfg.token_sampler), guidance=guidance)
        if float(cfg.rate) != pipeline.rate:  # the weights fix the rate: a different one would be ignored
            raise ValueError(f"rate={cfg.rate}: weights={cfg.weights} runs its world model at {pipeline.rate:g} Hz; "
                             f"leave rate at {pipeline.rate:g}")
        return pipeline
    for key in ("tokenizer_ckpt", "world_model_ckpt"):
        if not cfg.get(key):
            raise ValueError(f"mode={cfg.mode} needs {key}=<checkpoint> (and optionally decoder_ckpt=), or weights=")
    image_size = (cfg.data.height, cfg.data.width)
    return Gaia1Pipeline.from_checkpoints(cfg.tokenizer_ckpt, cfg.world_model_ckpt, cfg.decoder_ckpt,
                                          image_size=image_size, device=cfg.device, decoder_steps=cfg.decoder_steps,
                                          decoder_blend=decoder_blend(cfg), decoder_sampler=cfg.decoder_sampler,
                                          sampler=instantiate(cfg.token_sampler), guidance=guidance,
                                          upsample=cfg.upsample, rate=cfg.rate)


def load_gaia2(cfg: DictConfig) -> Gaia2Pipeline:
    """The GAIA-2 nets of `cfg` (a weights folder, or the two training checkpoints) with its solver and guidance."""
    g = cfg.model
    solver = (instantiate(g.sampler), instantiate(g.guidance))
    resize_mode = cfg.data.get("resize_mode", "crop")
    if cfg.get("weights"):
        given = [key for key in ("tokenizer_ckpt", "world_model_ckpt") if cfg.get(key)]
        if given:
            raise ValueError(f"weights={cfg.weights} replaces {', '.join(given)}; give one or the other")
        pipeline = Gaia2Pipeline.from_weights(cfg.weights, *solver, cfg.device, resize_mode, cfg.fps)
        size = (pipeline.encoder.height, pipeline.encoder.width)
        if size != (cfg.data.height, cfg.data.width):
            raise ValueError(f"weights={cfg.weights}: its video tokenizer was trained on {size} frames, but "
                             f"data.height × data.width is {(cfg.data.height, cfg.data.width)}; set them to match")
        return pipeline
    for key in ("tokenizer_ckpt", "world_model_ckpt"):
        if not cfg.get(key):
            raise ValueError(f"model=gaia2 mode={cfg.mode} needs {key}=<checkpoint of a GAIA-2 "
                             f"{'video tokenizer' if key == 'tokenizer_ckpt' else 'latent world model'}> "
                             "(or weights=<folder written by model=gaia2 mode=export>)")
    return Gaia2Pipeline.from_checkpoints(cfg.tokenizer_ckpt, cfg.world_model_ckpt, cfg.data.height, cfg.data.width,
                                          *solver, cfg.device, resize_mode, cfg.fps)
