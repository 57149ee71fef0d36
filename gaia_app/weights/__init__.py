"""Everything about loading weights, in one package (DESIGN.md §3, `weights/`).

- `checkpoints`: read a training checkpoint (a file or a sharded folder) without unpickling code.
- `targets`: the `_target_` allow-list, checked after interpolation, and building from a checked config.
- `folders`: weights folders (`<family>/<component>.safetensors` + `.yaml`): the shipped ones beside this file, export.
- `nets`: inference nets from a training checkpoint, by the component and state-dict prefixes the checkpoint
  records (`gaia_nets`, written at training time), without building a LightningModule.

The shipped weights themselves live beside these modules: `gaia1/`, `gaia2/`, `probes/` and MANIFEST.md.
"""
