# Entry points: `make demo` (train HIEROS on CartPole-v1), `make test` (the test suite), `make docs` (the Sphinx site).
# Each creates .venv on first use and reuses it afterwards.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
TORCH_VERSION := 2.13.0
TORCH_CPU_INDEX := https://download.pytorch.org/whl/cpu
TORCH_STAMP := $(VENV)/.torch-installed
DEMO_STAMP := $(VENV)/.demo-installed
DEV_STAMP := $(VENV)/.dev-installed

.PHONY: demo test docs lint clean-venv

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip

# With a CUDA GPU: the default torch build. Without one: the CPU build from PyTorch's CPU wheel index (the default
# index would bring the multi-GB CUDA build on Linux); where that index cannot be reached, the default index.
# The first try reads no pip configuration (PIP_CONFIG_FILE=/dev/null, --isolated), so that only the CPU index
# can supply the wheel, and gives up after one short attempt.
$(TORCH_STAMP): | $(PY)
	@if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then \
		echo "CUDA GPU found: installing torch==$(TORCH_VERSION) from the default index"; \
		$(PY) -m pip install -q torch==$(TORCH_VERSION); \
	elif PIP_CONFIG_FILE=/dev/null $(PY) -m pip install -q --isolated --timeout 10 --retries 0 \
			--index-url $(TORCH_CPU_INDEX) torch==$(TORCH_VERSION) >/dev/null 2>&1; then \
		echo "no CUDA GPU: installed torch==$(TORCH_VERSION) from PyTorch's CPU wheel index"; \
	else \
		echo "no CUDA GPU, and PyTorch's CPU wheel index ($(TORCH_CPU_INDEX)) could not be reached:"; \
		echo "installing torch==$(TORCH_VERSION) from the default index"; \
		$(PY) -m pip install -q torch==$(TORCH_VERSION); \
	fi
	@$(PY) -W ignore -c "import torch; print(f'torch {torch.__version__} (CUDA build: {torch.version.cuda is not None})')"
	touch $(TORCH_STAMP)

# The demo needs the package and its plotting/progress extra only.
$(DEMO_STAMP): pyproject.toml $(TORCH_STAMP)
	$(PY) -m pip install -q -e ".[extra]"
	touch $(DEMO_STAMP)

# Tests and docs need every extra (Atari, DMC, rl-zoo, Ray, rliable, Sphinx).
$(DEV_STAMP): pyproject.toml $(TORCH_STAMP)
	$(PY) -m pip install -q -e ".[dev]"
	touch $(DEV_STAMP)

# The demo picks its torch threads from the free CPUs (and says so) unless OMP_NUM_THREADS is set.
demo: $(DEMO_STAMP)
	$(PY) -m benchmarks.demo

test: $(DEV_STAMP)
	MUJOCO_GL=$${MUJOCO_GL:-egl} $(PY) -m pytest -q

# The Sphinx site into docs/_build/html, warnings as errors. (The code examples of README.md and docs/ run in the
# tests: tests/test_docs_examples.py.)
docs: $(DEV_STAMP)
	$(PY) -m sphinx -W --keep-going -q -b html docs docs/_build/html

lint: $(DEV_STAMP)
	$(PY) -m ruff format --check .
	$(PY) -m ruff check .

clean-venv:
	rm -rf $(VENV)
