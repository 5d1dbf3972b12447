# The two commands of the README: `make demo` and `make test`. Both create .venv and install the
# project (with its dev extra) when it is missing or pyproject.toml changed, and compile the planner's kernels.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench vcan-test rt-test clean chromium

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	@echo "compiling the planner's kernels (once per machine; cached beside planner/*.py for every later process)"
	@$(PY) -c 'import time; from planner.plan import warm_up; t = time.monotonic(); \
	  warm_up(lambda done, total, what: print(f"  kernels {done}/{total} after {time.monotonic() - t:.0f} s: {what}", flush=True))'
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/pvt demo

# the virtual-time tests on every core at once (pytest-xdist), then the ones in wall-clock time alone, then the
# isolated ones in a pytest process of their own (pyproject.toml's markers say which is which)
test: $(STAMP) lint chromium
	$(PY) -m pytest -q -n auto -m virtual
	$(PY) -m pytest -q -m "not virtual and not isolated"
	$(PY) -m pytest -q -m isolated

# Debian's chromium for the HTML report test (installed once when root and missing; else that test skips)
chromium:
	tools/ensure-chromium

lint: $(STAMP)
	$(VENV)/bin/ruff check planner streamer bus tests benchmarks tools examples
	$(VENV)/bin/mypy --strict planner streamer/core bus streamer/runtime/virtual.py streamer/runtime/trace.py streamer/runtime/homing.py streamer/runtime/extension.py \
		streamer/recording streamer/live streamer/view streamer/api
	$(PY) -m pytest -q -p no:cacheprovider tests/test_architecture.py  # import contracts, module sizes (issue 24)

# every benchmark; the soak runs 1 h of virtual time here (about 2 min), the full 8 h with
# `.venv/bin/python -m benchmarks.bench_soak --hours 8` (about 13 min)
bench: $(STAMP)
	PVT_SOAK_HOURS=1 $(PY) -m benchmarks

clean:
	rm -rf $(VENV) demo-out .pytest_cache .hypothesis

# the real-time tests (the drives in a process of their own, the cycle engine) 5 times in a row with a busy
# process beside them: they must not flake (issue 22); run it alone, it measures this machine's real time
rt-test: $(STAMP)
	$(PY) -c 'import subprocess, sys; hog = subprocess.Popen([sys.executable, "-c", "while True: pass"]); \
	  runs = [subprocess.run([sys.executable, "-m", "pytest", "-q", "-m", "realtime or isolated"]).returncode for _ in range(5)]; \
	  hog.kill(); print("rt-test: exit codes", runs); sys.exit(max(runs))'

vcan-test: $(STAMP)
	tools/vcan-vm/vcan-test.sh
