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
	$(BIN)/python -m pip install --quiet -e ".[test,sim,campaign]"
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
