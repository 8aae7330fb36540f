# Every target does its own set-up: a fresh machine needs only Python 3.11 and make.
PYTHON ?= python3
VENV ?= .venv
TORCH ?= torch==2.13.0
S ?= alice
PRESET ?=
PY := $(VENV)/bin/python
PIPELINE := $(VENV)/bin/pipeline
STAMP := $(VENV)/.installed

.PHONY: install test test-fast subject bench bench-stability evaluate-subjects smoke-paper report clean

$(STAMP): pyproject.toml Makefile
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip wheel
	# torch first, pinned, so no other build (e.g. a multi-GB CUDA one) is pulled in later.
	$(PY) -m pip install -q "$(TORCH)"
	$(PY) -m pip install -q -e ".[test,ray]"
	# mediapipe 0.10.14 ships its TFLite models; its declared extras are not needed.
	$(PY) -m pip install -q --no-deps mediapipe==0.10.14
	$(PY) -m pip install -q absl-py==2.5.1 attrs==26.1.0 flatbuffers==25.12.19 "protobuf==4.25.9"
	touch $(STAMP)

install: $(STAMP)

test: $(STAMP)
	$(PY) -m pytest -q -ra --durations=15 tests

test-fast: $(STAMP)
	$(PY) -m pytest -q -m "not slow" tests

subject: $(STAMP)
	$(PIPELINE) run -S $(S) $(if $(PRESET),--preset $(PRESET),)
	$(PIPELINE) report -S $(S)

report: $(STAMP)
	$(PIPELINE) report -S $(S)

bench: $(STAMP)
	$(PY) -m benchmarks.run_all

evaluate-subjects: $(STAMP)
	$(PY) -m benchmarks.evaluate_subjects --subjects $(or $(N),3)

smoke-paper: $(STAMP)
	$(PY) -m benchmarks.smoke_paper

bench-stability: $(STAMP)
	$(PY) -m benchmarks.stability

clean:
	rm -rf $(VENV) workspaces .pytest_cache
