# SensorBox: every target installs what it needs first.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DEMO_OUT ?= out/demo
PIP_INSTALL := $(BIN)/python -m pip install --quiet --no-cache-dir --no-compile -e '.[dev]'

.PHONY: setup demo test bench lint clean fixtures

setup: $(STAMP)

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --no-cache-dir --upgrade pip
	@# no byte-compiling at install (about 250 MB of .pyc for modules never imported) and no wheel cache
	@echo "$(PIP_INSTALL)"
	@$(PIP_INSTALL) || { \
	  echo "error: pip install failed; $(VENV) needs about 2 GB, and $$(df -Pm . | awk 'NR==2 {print $$4}') MB are free here" >&2; \
	  exit 1; }
	@bash tools/ensure_libusb.sh $(BIN)/python
	@touch $(STAMP)

DEMO_BAG := tests/fixtures/indoor_static_mcap

# The main job on the bundled example: a simulated recording (bag + exact truth) -> WideDepth training set.
demo: setup
	$(BIN)/sensorbox calib check $(DEMO_BAG).truth/rig.yaml --plot $(DEMO_OUT)/rig.png
	$(BIN)/sensorbox inspect $(DEMO_BAG) --rig $(DEMO_BAG).truth/rig.yaml
	@rm -rf $(DEMO_OUT)/widedepth  # a fresh dataset each run: ingest refuses to add to one made with other settings
	$(BIN)/sensorbox ingest $(DEMO_BAG) --rig $(DEMO_BAG).truth/rig.yaml --out $(DEMO_OUT)/widedepth
	@echo "Demo output: $(DEMO_OUT)/widedepth (WideDepth layout, dataset.yaml) and $(DEMO_OUT)/rig.png"

# The suite in two runs: everything else in parallel, then the live paths (sockets, threads on a
# clock, subprocess timing: marker `realtime`) one at a time, so two of them never share the cores.
# ROS 1's own rosbag (Debian's python3-rosbag) reads and writes bags in the interop tests.
# The suite's processes write their bytecode caches (__pycache__, ignored by git) even where
# PYTHONDONTWRITEBYTECODE is set: it starts about 100 Python processes (the commands' tests, ingest
# workers), and each would otherwise compile every module it imports again (2-3 CPU s a process).
test: setup
	@bash tools/ensure_ros1.sh
	env -u PYTHONDONTWRITEBYTECODE $(BIN)/python -m pytest -q -n 2 --dist loadgroup -m "not realtime" tests
	env -u PYTHONDONTWRITEBYTECODE $(BIN)/python -m pytest -q -m realtime tests

bench: setup
	$(BIN)/python bench/bench_models.py
	$(BIN)/python bench/bench_warp.py
	$(BIN)/python bench/bench_sim.py
	$(BIN)/python bench/bench_ingest.py --seconds 1
	$(BIN)/python bench/bench_ingest_stages.py
	$(BIN)/python bench/bench_livox.py
	$(BIN)/python bench/bench_render.py
	$(BIN)/python bench/bench_capture.py
	$(BIN)/python bench/bench_tradeoff.py
	$(BIN)/python bench/bench_stability.py
	$(BIN)/python bench/bench_dense.py
	$(BIN)/python bench/bench_dense_speed.py

# Regenerate the small simulated bags in tests/fixtures (deterministic: same bytes every time).
fixtures: setup
	$(BIN)/python -m sensorbox.sim.fixtures

lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

clean:
	rm -rf $(VENV) out .pytest_cache .mypy_cache .ruff_cache
