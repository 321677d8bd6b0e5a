# Two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: venv demo test bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet -e ".[test,opencv,sim,campaign]"
	$(BIN)/lunarloc warm-up
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/lunarloc demo --out demo-output --overwrite

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/lunarloc bench pairs --data ../shared/data/lunarloc-data --out bench-output --overwrite

clean:
	rm -rf $(VENV) demo-output bench-output build *.egg-info src/*.egg-info src/lunarloc/association/_aot_kernels*

# FastSAM, the paper's segmenter (optional; no weights are fetched). torch's CPU build goes
# first so that nothing pulls the CUDA one; torchvision only for its metadata (see
# docs/perception.md). Then its tests and the CPU speed table on weightless networks.
.PHONY: fastsam
fastsam: $(STAMP)
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet --no-deps torchvision==0.28.0
	$(BIN)/python -m pip install --quiet -e ".[test,opencv,sim,campaign,fastsam-onnx]"
	$(BIN)/python -m pytest -q tests/test_fastsam.py
	$(BIN)/python benchmarks/fastsam_speed.py
