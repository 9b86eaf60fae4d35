# Two set-up commands: `make demo` and `make test` (see README.md).
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test install clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip setuptools wheel
	# CPU torch first: an unpinned torch would download a multi-GB CUDA build.
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[test]'
	# BlazePose models: fetched once from the mediapipe wheel on PyPI (models only,
	# sha256-checked) and converted to ONNX by our own converter.
	$(VENV)/bin/uuomocap prior fetch-models
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/uuomocap demo

# Two workers (the CI machine has 2 cores); a file stays on one worker so its module fixtures
# (generated sessions, solves) are built once.
test: $(STAMP)
	$(PY) -m pytest -n 2 --dist loadfile --no-loadscope-reorder --durations=15

clean:
	rm -rf $(VENV) build *.egg-info
