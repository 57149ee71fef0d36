# Two commands on a fresh machine with Python ≥ 3.10 and make:
#   make demo   set up .venv and run the main job on the built-in synthetic data
#   make test   set up .venv with the dev extra and run the tests
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
PY := $(VENV)/bin/python
CONSTRAINTS := requirements/constraints.txt
DEMO_DIR := outputs/demo
PYTEST_ARGS ?=

.PHONY: demo demo-train test test-slow test-rehearsal test-all lint install install-dev benchmarks clean reproduce

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

# stamps: re-install only when the dependency files change
$(VENV)/.installed: pyproject.toml $(CONSTRAINTS) | $(PY)
	$(PY) -m pip install --quiet -c $(CONSTRAINTS) -e .
	touch $@

$(VENV)/.installed-dev: pyproject.toml $(CONSTRAINTS) | $(PY)
	$(PY) -m pip install --quiet -c $(CONSTRAINTS) -e '.[dev]'
	touch $@ $(VENV)/.installed

install: $(VENV)/.installed
install-dev: $(VENV)/.installed-dev

# The main job: GAIA-1 from the shipped reference weights (gaia_app/weights/gaia1, made by `make reproduce`;
# docs/reference.md). One held-out context of the synthetic world steered four ways (brake / accelerate / left /
# right) and generation from the prompts "night" and "snow" against no prompt, as mp4 + PNG strips + one .rrd,
# then the controllability table with the shipped probes (a smaller protocol than the MANIFEST's 32 contexts).
# The showcase decodes with the shipped video decoder at the world model's 6.25 Hz: its conditional mean over 8 noise
# draws in 4 antithetic pairs, which beats frame-by-frame decoding on flicker like the shipped setting (16 independent
# draws) at half its cost (docs/video_decoder.md); the controllability table keeps the tokenizer's frame-by-frame
# decoding its probes were checked on.
# The recipe's protocol (gaia_app/tasks/reproduce.py): 4 context frames, 1.25 s of future, guidance scale 1.5
# (3 for rollouts prompted with text).
PROTOCOL := context.frames=4 seconds=1.25 guidance.scale=1.5 guidance.text_scale=3
DEMO_CONTROLLABILITY := controllability.contexts=8 controllability.text_repeats=8 controllability.floor_repeats=32 \
	controllability.real_clips=32 \
	'controllability.prompts.weather=[clear,snow]'
# GAIA-2 (gaia_app/weights/gaia2): one held-out 3-camera scene rolled out 3 chunks (1.92 s at 12.5 Hz) with a car
# cut in 9 m ahead (model.add_agents) and guidance ×3 on the agent boxes
GAIA2_DEMO := model.chunks=3 num_futures=1 model.guidance.scale=3 \
	'model.add_agents=[{category: car, centre: [9, 0, 0.75], size: [4.5, 1.9, 1.5]}]'
# The showcase and the controllability table run side by side, each on half the cores: these small models use two
# threads poorly, so on 2 cores the pair finishes in about 155 s instead of 195 s one after the other
# (docs/benchmarks.md). The showcase's log goes to $(DEMO_DIR)/showcase.log (printed if it fails).
HALF_CORES = $(shell $(PYTHON) -c "import os; print(max(1, (os.cpu_count() or 2) // 2))")
demo: install
	@mkdir -p $(DEMO_DIR)
	@echo "showcase (log: $(DEMO_DIR)/showcase.log) and controllability side by side, $(HALF_CORES) thread(s) each"
	@OMP_NUM_THREADS=$(HALF_CORES) $(PY) generate.py mode=showcase weights=gaia1 $(PROTOCOL) upsample=0 \
		decoder_sampler=antithetic_mean decoder_steps=8 decoder_blend.probability=0 token_sampler.progress=false \
		hydra.run.dir=$(DEMO_DIR)/showcase > $(DEMO_DIR)/showcase.log 2>&1 & showcase=$$!; \
	trap 'kill $$showcase 2>/dev/null' INT TERM; \
	OMP_NUM_THREADS=$(HALF_CORES) $(PY) generate.py mode=controllability weights=gaia1 $(PROTOCOL) $(DEMO_CONTROLLABILITY) \
		hydra.run.dir=$(DEMO_DIR)/controllability; table=$$?; \
	if ! wait $$showcase; then tail -n 40 $(DEMO_DIR)/showcase.log; echo "the showcase failed (above)"; exit 1; fi; \
	exit $$table
	$(PY) generate.py model=gaia2 mode=rollout weights=gaia2 data=synthetic_rig $(GAIA2_DEMO) \
		hydra.run.dir=$(DEMO_DIR)/gaia2
	@echo "steered futures: $(DEMO_DIR)/showcase/commands/{grid.mp4,strip.png}; prompts: $(DEMO_DIR)/showcase/prompts/"
	@echo "controllability (ceiling / model / floor): $(DEMO_DIR)/controllability/controllability.md"
	@echo "GAIA-2, a car cut in ahead on 3 cameras: $(DEMO_DIR)/gaia2/{grid.mp4,sample_0.mp4}"
	@echo "Rerun: .venv/bin/rerun $(DEMO_DIR)/showcase/showcase.rrd $(DEMO_DIR)/gaia2/rollout.rrd"

# The whole chain trained from scratch at smoke size (minutes, not the recipe): tokenizer, token cache, world
# model, video decoder, rollouts through the video decoder and the tokenizer, and a smoke-size controllability
# table. Every step reuses what an earlier run finished (ckpt_path=last; tokenize skips clips on disk).
TRAIN_DIR := outputs/demo_train
TRAIN_CKPTS := tokenizer_ckpt=$(TRAIN_DIR)/tokenizer/checkpoints/last.ckpt \
	world_model_ckpt=$(TRAIN_DIR)/world_model/checkpoints/last.ckpt \
	decoder_ckpt=$(TRAIN_DIR)/video_decoder/checkpoints/last.ckpt
TRAIN_CONTROLLABILITY := controllability.probe_clips=48 controllability.probe_steps=400 controllability.contexts=4 \
	controllability.text_repeats=2 controllability.floor_repeats=4 controllability.real_clips=24 \
	'controllability.prompts.weather=[clear,snow]'
demo-train: install
	$(PY) train.py experiment=gaia1/demo/tokenizer hydra.run.dir=$(TRAIN_DIR)/tokenizer ckpt_path=last
	$(PY) generate.py mode=tokenize ckpt=$(TRAIN_DIR)/tokenizer/checkpoints/last.ckpt data=synthetic \
		data.source.clip_len=32 fps=6.25 max_clips=96 out_dir=$(TRAIN_DIR)/tokens hydra.run.dir=$(TRAIN_DIR)/tokenize
	$(PY) train.py experiment=gaia1/demo/world_model hydra.run.dir=$(TRAIN_DIR)/world_model ckpt_path=last \
		data.path=$(TRAIN_DIR)/tokens/train
	$(PY) train.py experiment=gaia1/demo/video_decoder hydra.run.dir=$(TRAIN_DIR)/video_decoder ckpt_path=last \
		model.tokenizer_ckpt=$(TRAIN_DIR)/tokenizer/checkpoints/last.ckpt
	$(PY) generate.py mode=action $(TRAIN_CKPTS) speed=accelerate curvature=left decoder_steps=4 \
		hydra.run.dir=$(TRAIN_DIR)/rollout_action
	$(PY) generate.py mode=text $(TRAIN_CKPTS) decoder_ckpt=null 'prompt="It is night. It is raining."' \
		hydra.run.dir=$(TRAIN_DIR)/rollout_text
	$(PY) generate.py mode=controllability $(TRAIN_CKPTS) decoder_ckpt=null hydra.run.dir=$(TRAIN_DIR)/controllability \
		$(TRAIN_CONTROLLABILITY)
	@echo "Rerun: .venv/bin/rerun $(TRAIN_DIR)/rollout_action/rollout.rrd $(TRAIN_DIR)/rollout_text/rollout.rrd"

# The GAIA-1 reference recipe from scratch (docs/reference.md): tokenizer, token cache, world model, held-out
# cross-entropy, controllability with probes, export to gaia_app/weights/gaia1 and gaia_app/weights/MANIFEST.md.
# Resumable: run it again after an interruption. About 3 hours on 2 CPU cores. GPU=1 adds the two fine-tunes that made
# version 6 of the shipped weights: one on the GPU (≈ 8 min on one H200; conf/experiment/gaia1/reference/
# world_model_finetune_gpu.yaml), then one on the CPU on clips with less snow (≈ 18 min; world_model_less_snow.yaml).
reproduce: install
	$(PY) -m gaia_app.tasks.reproduce --out outputs/reference --weights gaia_app/weights/gaia1 $(if $(GPU),--gpu)

# lint first (ruff, [tool.ruff] in pyproject.toml: a lint error fails the target before any test runs), then one
# pytest-xdist worker per logical CPU (TEST_WORKERS=0 runs in one process); --dist loadscope keeps each test module
# on one worker, so module-scoped fixtures (trained tiny models) are built once; --no-loadscope-reorder hands the
# modules out in collection order, which tests/conftest.py starts with the longest ones.
# Three tiers, by marker (docs/benchmarks.md, "Three tiers"):
# - `make test`: the quick tier, everything not marked slow or rehearsal;
# - `make test-slow`: multi-process DDP/FSDP2/DeepSpeed runs, the learning runs scored on held-out data, the
#   closed-loop pin, benchmark scripts on the shipped weights; run it before landing a change (the session's closing
#   note says it passed) and after changing what it covers;
# - `make test-rehearsal`: CPU rehearsals of GPU work (the lease scripts' dry runs, one step of each paper-size
#   preset); run it before a GPU lease and after changing a lease script or a paper preset.
# CI runs `make test`: with the slow tier it took 34 min on a 2-core AVX2 machine, over its 25 (docs/benchmarks.md).
# `make test TEST_MARKS="not rehearsal"` runs the quick and slow tiers in one session.
TEST_WORKERS ?= logical
TEST_MARKS ?= not slow and not rehearsal
PYTEST_XDIST = $(PY) -m pytest -n $(TEST_WORKERS) --dist loadscope --no-loadscope-reorder
test: install-dev lint
	$(PYTEST_XDIST) -m "$(TEST_MARKS)" $(PYTEST_ARGS)

test-slow: install-dev
	$(PYTEST_XDIST) -m "slow and not rehearsal" $(PYTEST_ARGS)

test-rehearsal: install-dev
	$(PYTEST_XDIST) -m rehearsal $(PYTEST_ARGS)

test-all: install-dev lint
	$(PYTEST_XDIST) $(PYTEST_ARGS)

lint: install-dev
	$(VENV)/bin/ruff check .

benchmarks: install-dev
	$(PY) benchmarks/bench_synthetic.py

clean:
	rm -rf $(VENV) outputs .pytest_cache
