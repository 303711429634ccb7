# Every target builds .venv by itself: on a fresh clone `make demo` and
# `make test` are the only commands a user types. The venv includes the cluster extra
# (Dask) so CI runs the real LocalCluster tests of tests/test_cluster.py.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test bench lint venv clean xvfb

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[host,device,dev,cluster]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/eigencast demo $(DEMO_ARGS)

test: $(STAMP)
	SDL_VIDEODRIVER=dummy $(BIN)/python -m pytest -m "not slow" -q $(TEST_ARGS)

bench: $(STAMP)
	$(BIN)/python benchmarks/run_all.py

lint: $(STAMP)
	$(BIN)/ruff check host protocol device_runtime tests benchmarks scripts research

# Debian's Xvfb for the real-window test; needs root (or an existing install).
xvfb:
	command -v Xvfb >/dev/null || (apt-get update -qq && apt-get install -y -qq xvfb xdotool)

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
