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

# The LAC leaderboard's environment (docs/lac-environment.md): Python 3.10, numpy 1.x and
# opencv-python 4.10.0.84 installed first; installing lunarloc must keep both (no numpy 2, no
# second OpenCV wheel), then the test suite runs there. Python 3.10 from PATH or pyenv; skipped
# with a message when there is none or when the pinned wheels cannot be downloaded (they are
# cp310 wheels from PyPI). PY310_REQUIRED=1 turns both skips into failures.
VENV310      ?= .venv-py310
PY310_NUMPY  ?= 1.26.4
PY310_OPENCV ?= 4.10.0.84
# pytest arguments. By default the three slowest parts are left out (the numba warm-up of every
# kernel, the multi-rover runs, one shifted-reference agent drive: ~30 % of the suite's time,
# what they run on 3.10 / numpy 1.x / OpenCV 4.x, the rest of the suite runs too);
# PY310_PYTEST=-q runs everything.
PY310_PYTEST ?= -q --ignore=tests/test_multirover.py \
	--deselect tests/test_warmup.py::test_warm_up_reaches_every_search_kernel \
	--deselect tests/test_online_component.py::test_enum_camera_keys_and_a_shifted_reference
# the first candidate that runs as 3.10 (a pyenv shim on PATH fails when 3.10 is not selected)
PY310_FIND   := for p in python3.10 $$(ls -d $${PYENV_ROOT:-$$HOME/.pyenv}/versions/3.10.*/bin/python 2>/dev/null | sort -rV); do \
	  "$$p" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 10))' >/dev/null 2>&1 && { command -v "$$p"; break; }; done
PY310_PINS   := numpy==$(PY310_NUMPY) opencv-python==$(PY310_OPENCV)

.PHONY: test-py310
test-py310:
	@py=$$($(PY310_FIND)); \
	if [ -z "$$py" ]; then \
	  echo "test-py310: SKIPPED, no Python 3.10 (python3.10 on PATH or pyenv's versions/3.10.*)"; \
	  [ -z "$(PY310_REQUIRED)" ] || exit 1; exit 0; fi; \
	set -e; \
	if [ ! -x $(VENV310)/bin/python ] || ! $(VENV310)/bin/python -c 'import sys; sys.exit(sys.version_info[:2] != (3, 10))'; then \
	  rm -rf $(VENV310); "$$py" -m venv $(VENV310); fi; \
	if [ ! -f $(VENV310)/.installed ] || [ pyproject.toml -nt $(VENV310)/.installed ] \
	   || [ "$$(cat $(VENV310)/.installed)" != "$(PY310_PINS)" ]; then \
	  if ! $(VENV310)/bin/python -m pip install --quiet $(PY310_PINS); then \
	    echo "test-py310: SKIPPED, cannot install $(PY310_PINS) (no index holding cp310 wheels reachable)"; \
	    [ -z "$(PY310_REQUIRED)" ] || exit 1; exit 0; fi; \
	  $(VENV310)/bin/python -m pip install --quiet -e ".[test,sim]"; \
	  echo "$(PY310_PINS)" > $(VENV310)/.installed; fi; \
	$(VENV310)/bin/python -m pip list --format=freeze 2>/dev/null | grep -iE '^(numpy|opencv[a-z-]*)==' | sort; \
	$(VENV310)/bin/python -c 'import sys, numpy, cv2; from importlib.metadata import distributions as d; \
	cv = sorted(x.metadata["Name"] for x in d() if x.metadata["Name"].lower().startswith("opencv")); \
	ok = numpy.__version__ == "$(PY310_NUMPY)" and cv == ["opencv-python"] and cv2.__version__ == "$(PY310_OPENCV)".rsplit(".", 1)[0]; \
	print("test-py310: Python", sys.version.split()[0], "numpy", numpy.__version__, "cv2", cv2.__version__, "from", cv); \
	sys.exit(0 if ok else "test-py310: installing lunarloc changed the pinned numpy/OpenCV")'; \
	$(VENV310)/bin/python -m pytest $(PY310_PYTEST)
