# The two commands of the README: `make demo` and `make test`. Both create .venv and install the project when it
# is missing or pyproject.toml changed (`make test` and the other targets also its dev extra): with uv (installed
# into the venv first), which installs the same wheels as pip in a fraction of the time (measured here from empty
# caches: 9 s, pip 53 s), or with pip where uv cannot be had. The planner's kernels (planner/jit.py) compile once
# per machine, about a minute: `make test` compiles them first; a machine's first `make demo` plans with them
# interpreted (2-4 s for the demo's job, NUMBA_DISABLE_JIT=1) so that motion shows at once, and compiles them
# after it.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
DEV := $(VENV)/.installed-dev
KERNELS := $(VENV)/.kernels
# uv when it installs (put into the venv by the system's pip: a venv without pip is made in 0.1 s, with it in 5 s),
# else pip (then the venv's own, from ensurepip). $(2): --compile-bytecode, as pip does, for the tests (they start
# hundreds of processes) and wherever PYTHONDONTWRITEBYTECODE is set (this machine, CI): nothing would write the
# .pyc files later, and every process would compile what it imports (measured: 3.4-5.3 s to import the demo's
# modules without them, 1.1 s with). Elsewhere the demo's first imports write the ones it needs.
BYTECODE := $(if $(PYTHONDONTWRITEBYTECODE),--compile-bytecode)
INSTALL = (([ -x $(VENV)/bin/uv ] || $(PYTHON) -m pip --python $(PY) install -q --disable-pip-version-check uv) \
	  && $(VENV)/bin/uv pip install -q $(2) --python $(PY) -e '$(1)') \
	  || ($(PY) -m ensurepip -q && $(PY) -m pip install -q -e '$(1)')

.PHONY: demo test lint bench vcan-test rt-test clean chromium

$(STAMP): pyproject.toml
	$(PYTHON) -m venv --without-pip $(VENV)
	@echo "installing pvt and its dependencies into $(VENV)"
	$(call INSTALL,.,$(BYTECODE))
	touch $(STAMP)

$(DEV): $(STAMP)
	@echo "installing the dev extra (tests, lint) into $(VENV)"
	$(call INSTALL,.[dev],--compile-bytecode)
	touch $(DEV)

$(KERNELS): $(STAMP)
	$(PY) -m planner.plan
	touch $(KERNELS)

demo: $(STAMP)
	@if [ -e $(KERNELS) ]; then $(VENV)/bin/pvt demo; else \
	  echo "make demo: this machine's first run plans with the planner's kernels interpreted; they compile after it"; \
	  NUMBA_DISABLE_JIT=1 $(VENV)/bin/pvt demo; status=$$?; $(MAKE) --no-print-directory $(KERNELS); exit $$status; fi

# every test that does not judge real time on every core at once (pytest-xdist: the virtual-time ones, and the
# services, clients and CLI whose waits are generous), then the real-time and wall-clock ones alone, then the
# isolated ones in a pytest process of their own (pyproject.toml's markers say which is which); first the kernels,
# lint and chromium side by side (each takes about a minute on a first run). Measured here: the 861 tests after the
# virtual-time ones took 504 s one at a time; the services' 837 of them take 241 s on both cores (285 s with a CPU
# hog beside them, all passed), the 24 real-time ones about 100 s alone
test: $(DEV)
	$(MAKE) --no-print-directory -j3 $(KERNELS) lint chromium
	$(PY) -m pytest -q -n auto -m "not realtime and not wallclock and not isolated"
	$(PY) -m pytest -q -m "realtime or wallclock"
	$(PY) -m pytest -q -m isolated

# Debian's chromium for the HTML report test (installed once when root and missing; else that test skips)
chromium:
	tools/ensure-chromium

lint: $(DEV)
	$(VENV)/bin/ruff check planner streamer bus tests benchmarks tools examples
	$(VENV)/bin/mypy --strict planner streamer/core bus streamer/runtime streamer/report.py \
		streamer/recording streamer/live streamer/view streamer/api
	$(PY) -m pytest -q -p no:cacheprovider tests/test_architecture.py  # import contracts, module sizes (issue 24)

# every benchmark; the soak runs 1 h of virtual time here (about 2 min), the full 8 h with
# `.venv/bin/python -m benchmarks.bench_soak --hours 8` (about 13 min)
bench: $(DEV) $(KERNELS)
	PVT_SOAK_HOURS=1 $(PY) -m benchmarks

clean:
	rm -rf $(VENV) demo-out .pytest_cache .hypothesis

# the real-time tests (the drives in a process of their own, the cycle engine), then the isolated ones in a
# pytest process of their own (as `make test` runs them), 5 times in a row with a busy process beside them: they
# must not flake (issue 22); run it alone, it measures this machine's real time
rt-test: $(DEV) $(KERNELS)
	$(PY) -c 'import subprocess, sys; hog = subprocess.Popen([sys.executable, "-c", "while True: pass"]); \
	  suite = lambda m: subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", m]).returncode; \
	  runs = [(suite("realtime"), suite("isolated")) for _ in range(5)]; \
	  hog.kill(); print("rt-test: exit codes (realtime, isolated) per run", runs); sys.exit(max(map(max, runs)))'

vcan-test: $(DEV)
	tools/vcan-vm/vcan-test.sh
