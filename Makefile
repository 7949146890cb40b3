# cobgs: the two commands a fresh machine needs are `make demo` and `make test`.
# Everything is installed into a private virtual environment ($(VENV)).

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip --quiet
STAMP  := $(VENV)/.cobgs-installed
# The local CPU wheel of PyTorch; installed before the package so that pip sees the
# torch requirement as satisfied and never downloads the CUDA build.
TORCH_SPEC ?= torch==2.13.0
PYTEST_ARGS ?=

.PHONY: install build test demo bench report clean help chromium parity gpu-check

help:
	@echo "make demo    run the embedded demo workflow (installs and builds first)"
	@echo "make test    install, build the native extension, run the test suite"
	@echo "make bench   run the benchmark workflow and tests/benchmarks"
	@echo "make report  regenerate the HTML report of the demo workflow"

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -c "import torch" 2>/dev/null || $(PIP) install "$(TORCH_SPEC)"
	$(PIP) install -e ".[dev,ray]"
	touch $(STAMP)

install: $(STAMP)

build: install
	$(VENV)/bin/cobgs build

# Headless Chromium for the report's browser tests (Debian's package, ~25 s once, root only);
# without it those tests skip, saying why.
chromium:
	@test -x /usr/bin/chromium || [ "$$(id -u)" != 0 ] || DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium >/dev/null 2>&1 \
	  || { apt-get update -q >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium >/dev/null; } \
	  || echo "note: could not install chromium; the browser tests will be skipped"

test: build chromium
	$(PY) -m pytest -m "not slow and not gpu" $(PYTEST_ARGS)

demo: build
	$(VENV)/bin/cobgs run workflows/demo.toml
	$(VENV)/bin/cobgs export workflows/demo.toml --to runs/demo --turntables 24
	$(VENV)/bin/cobgs report workflows/demo.toml --turntables 24

bench: build
	$(VENV)/bin/cobgs run workflows/synthetic_bench.toml
	$(VENV)/bin/cobgs export workflows/synthetic_bench.toml --to runs/synthetic_bench --no-ply
	$(VENV)/bin/cobgs report workflows/synthetic_bench.toml
	@echo "micro-benchmarks (run one by one): $$(ls tests/benchmarks/bm_*.py | tr '\n' ' ')"

# Parity with the upstream model code (not in CI: it needs a venv with a torch build, Meta's
# or Grounded-SAM-2's sam2, groundingdino-py and transformers<5, ~5 GB). Set PARITY_PY to that
# venv's python (it also needs onnx, onnxruntime, opencv-python-headless, tokenizers, pytest)
# and SAM2_CODE to a Grounded-SAM-2 checkout to compare with the predictor the authors ran.
parity:
	@test -n "$(PARITY_PY)" || { echo "set PARITY_PY=/path/to/venv/bin/python (README: parity with upstream)"; exit 2; }
	PYTHONPATH=$(if $(SAM2_CODE),$(SAM2_CODE):)$(CURDIR) $(PARITY_PY) -m pytest -m slow -s -p no:cacheprovider \
	  tests/masks/test_sam2_parity.py tests/masks/test_gdino_parity.py

report: build
	$(VENV)/bin/cobgs report workflows/demo.toml --turntables 24

# The whole GPU check (not in CI: it needs a CUDA device): build, the CUDA parity tests of both
# blending paths, the kernel benchmark against gsplat, fern on both paths while time is left.
# Results in $(GPU_CHECK_OUT); tests/benchmarks/gpu_check.sh lists GPU_CHECK_ARGS (--wheels,
# --fern-scene, --fern-images, --budget-s).
GPU_CHECK_OUT ?= runs/gpu_check
GPU_CHECK_ARGS ?=
gpu-check:
	PYTHON=$(if $(wildcard $(PY)),$(PY),$(PYTHON)) bash tests/benchmarks/gpu_check.sh $(GPU_CHECK_OUT) $(GPU_CHECK_ARGS)

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
