# Two commands on a fresh machine with Python ≥ 3.10 and make:
#   make demo   set up .venv and run the main job on the built-in synthetic data
#   make test   set up .venv with the dev extra and run the tests
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
PY := $(VENV)/bin/python
CONSTRAINTS := requirements/constraints.txt
DEMO_DIR := outputs/demo
PYTEST_ARGS ?=

.PHONY: demo test install install-dev benchmarks clean reproduce

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

# The main job, GAIA-1 end to end on the built-in synthetic world (docs/generate.md): train the tiny
# tokenizer, tokenize clips at 6.25 Hz, train the world model and the video decoder, then generate an
# action-conditioned rollout (through the video decoder, 25 Hz) and a text-conditioned one (frames decoded
# one by one by the tokenizer, 6.25 Hz), and score action / text adherence with probes. Every step reuses what an earlier run finished
# (ckpt_path=last resumes or skips a training run; tokenize skips clips already on disk).
DEMO_CKPTS := tokenizer_ckpt=$(DEMO_DIR)/tokenizer/checkpoints/last.ckpt \
	world_model_ckpt=$(DEMO_DIR)/world_model/checkpoints/last.ckpt \
	decoder_ckpt=$(DEMO_DIR)/video_decoder/checkpoints/last.ckpt
# a smoke-size controllability table: sampling 128 rollouts of 448-token frames for the default protocol (32 contexts ×
# 4 commands) takes about 6 min per frame on 2 cores; docs/generate.md
DEMO_CONTROLLABILITY := controllability.probe_clips=48 controllability.probe_steps=400 controllability.contexts=4 \
	controllability.text_repeats=2 controllability.real_clips=24 'controllability.prompts.weather=[clear,snow]'
demo: install
	$(PY) train.py experiment=gaia1/demo/tokenizer hydra.run.dir=$(DEMO_DIR)/tokenizer ckpt_path=last
	$(PY) generate.py mode=tokenize ckpt=$(DEMO_DIR)/tokenizer/checkpoints/last.ckpt data=synthetic \
		data.source.clip_len=32 fps=6.25 max_clips=96 out_dir=$(DEMO_DIR)/tokens hydra.run.dir=$(DEMO_DIR)/tokenize
	$(PY) train.py experiment=gaia1/demo/world_model hydra.run.dir=$(DEMO_DIR)/world_model ckpt_path=last \
		data.path=$(DEMO_DIR)/tokens/train
	$(PY) train.py experiment=gaia1/demo/video_decoder hydra.run.dir=$(DEMO_DIR)/video_decoder ckpt_path=last \
		model.tokenizer_ckpt=$(DEMO_DIR)/tokenizer/checkpoints/last.ckpt
	$(PY) generate.py mode=action $(DEMO_CKPTS) speed=accelerate curvature=left decoder_steps=4 \
		hydra.run.dir=$(DEMO_DIR)/rollout_action
	$(PY) generate.py mode=text $(DEMO_CKPTS) decoder_ckpt=null 'prompt="It is night. It is raining."' \
		hydra.run.dir=$(DEMO_DIR)/rollout_text
	$(PY) generate.py mode=controllability $(DEMO_CKPTS) decoder_ckpt=null hydra.run.dir=$(DEMO_DIR)/controllability \
		$(DEMO_CONTROLLABILITY)
	@echo "demo outputs: $(DEMO_DIR)/rollout_{action,text}/{grid,future_0,future_1}.mp4 (real clip | futures)"
	@echo "controllability (probes on rollouts, with ceiling and floor): $(DEMO_DIR)/controllability/controllability.md"
	@echo "Rerun: .venv/bin/rerun $(DEMO_DIR)/rollout_action/rollout.rrd $(DEMO_DIR)/rollout_text/rollout.rrd"

# The GAIA-1 reference recipe from scratch (docs/reference.md): tokenizer, token cache, world model, held-out
# cross-entropy, controllability with probes, export to gaia_app/weights/gaia1 and gaia_app/weights/MANIFEST.md.
# Resumable: run it again after an interruption. About 3 hours on 2 CPU cores.
reproduce: install
	$(PY) -m gaia_app.tasks.reproduce --out outputs/reference --weights gaia_app/weights/gaia1

test: install-dev
	$(PY) -m pytest $(PYTEST_ARGS)

benchmarks: install-dev
	$(PY) benchmarks/bench_synthetic.py

clean:
	rm -rf $(VENV) outputs .pytest_cache
