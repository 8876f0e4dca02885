# calfit: set-up, demo and tests on a fresh Debian machine.
#   make demo   set-up + the main job (built-in phantom leg, end to end)
#   make test   set-up + the whole fast test suite (C++ unit tests + pytest)
#   make accept-gold   the engine's gold standards (tests/engine/gold/*.json) written again: take a reviewed change
# Other targets: setup, test-slow, bench, fuzz (100,000 mutated decks), sanitize (ASan + UBSan build, ctest and
# the fuzz corpus), clean.

SHELL := /bin/bash
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
DEBIAN_PACKAGES := g++ cmake make pkg-config libeigen3-dev libsuitesparse-dev libopenblas-dev calculix-ccx
ENGINE_SOURCES := $(shell find solver_cpp correlation_cpp -type f \( -name '*.cpp' -o -name '*.hpp' -o -name 'CMakeLists.txt' \))
# the editable install maps each module to its file: a module added or moved needs it made again (seconds)
PACKAGE_SOURCES := $(shell find orchestrator -name "*.py")

.PHONY: setup system-packages demo test test-slow test-cpp accept-gold bench fuzz sanitize clean

setup: system-packages $(VENV)/.installed

# Debian packages: installed with apt-get when root, otherwise one clear instruction.
system-packages:
	@missing=""; for p in $(DEBIAN_PACKAGES); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ]; then \
	    echo "installing Debian packages:$$missing"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; \
	  else \
	    echo "Missing Debian packages:$$missing. Run: sudo apt-get install$$missing" >&2; exit 1; \
	  fi; \
	fi

$(VENV)/bin/python:
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip

$(VENV)/.installed: $(VENV)/bin/python pyproject.toml CMakeLists.txt $(ENGINE_SOURCES) $(PACKAGE_SOURCES)
	$(PY) -m pip install -q -e '.[test]'
	touch $@

demo: setup
	$(VENV)/bin/calfit demo

test-cpp: setup
	ctest --test-dir $$(ls -d build/*/ | head -n 1) --output-on-failure

# The fast suite runs on every core (pytest-xdist): a module's tests stay on one worker, so its fixtures are
# built once. Alone on this 2-core machine it took 630 s; on two workers, 408 s.
test: test-cpp
	$(PY) -m pytest -m "not slow" -q --durations=15 -n auto --dist loadscope

accept-gold: setup
	$(PY) tests/engine/test_engine_gold.py --accept

test-slow: setup
	$(PY) -m pytest -m slow -q --durations=15

fuzz: setup
	$(PY) tests/support/fuzz_decks.py --inputs 100000 --seed 1

SANITIZE_BUILD := build-sanitize
sanitize: setup
	cmake -S . -B $(SANITIZE_BUILD) -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCALFIT_SANITIZE=ON
	cmake --build $(SANITIZE_BUILD) -j $$(nproc)
	ASAN_OPTIONS=detect_leaks=1 UBSAN_OPTIONS=print_stacktrace=1 ctest --test-dir $(SANITIZE_BUILD) --output-on-failure
	ASAN_OPTIONS=detect_leaks=1 UBSAN_OPTIONS=print_stacktrace=1 $(PY) tests/support/fuzz_decks.py \
	  --engine $(SANITIZE_BUILD)/solver_cpp/calfit-fe --inputs 3000 --seed 1 --timeout 120

bench: setup
	$(PY) -m pip install --quiet felupe pyvale
	for b in benchmarks/*.py; do $(PY) $$b || exit 1; done

clean:
	rm -rf build $(SANITIZE_BUILD) $(VENV) *.egg-info
