# Two commands on a fresh machine with Python ≥ 3.10 and make:
#   make demo   set up .venv and run the main job on the built-in synthetic data
#   make test   set up .venv with the dev extra and run the tests
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
PY := $(VENV)/bin/python
CONSTRAINTS := requirements/constraints.txt
DEMO_DIR := outputs/demo
PYTEST_ARGS ?=

.PHONY: demo test install install-dev benchmarks clean

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

# Until the full GAIA-1 pipeline lands, the main job is: train the tiny GAIA-1 image tokenizer on the
# synthetic world, then reconstruct held-out clips with it. ckpt_path=last makes a second run reuse it.
demo: install
	$(PY) train.py experiment=gaia1/tokenizer_tiny hydra.run.dir=$(DEMO_DIR)/tokenizer ckpt_path=last
	$(PY) generate.py ckpt=$(DEMO_DIR)/tokenizer/checkpoints/last.ckpt hydra.run.dir=$(DEMO_DIR)/reconstruct \
		data.val_source.clip_len=50 num_clips=2
	@echo "demo outputs: $(DEMO_DIR)/reconstruct/*.mp4 (input | reconstruction)"
	@echo "Rerun: .venv/bin/rerun $(DEMO_DIR)/tokenizer/run.rrd $(DEMO_DIR)/reconstruct/reconstruction.rrd"

test: install-dev
	$(PY) -m pytest $(PYTEST_ARGS)

benchmarks: install-dev
	$(PY) benchmarks/bench_synthetic.py

clean:
	rm -rf $(VENV) outputs .pytest_cache
