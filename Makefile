# galvoscan: two commands on a fresh machine.
#   make demo   set up .venv if needed, then run the main job on the simulated rig
#   make test   set up .venv if needed, then lint and run every test
#   make firmware  build the galvo board firmware (.hex) and its simavr harness (firmware/)
#
# Setup is split into stamped steps so that a second run with nothing changed only checks.

SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP_DEPS := $(VENV)/.stamp-deps
STAMP_MSGS := $(VENV)/.stamp-msgs
STAMP_SRC := $(VENV)/.stamp-src
STAMP_APT := $(VENV)/.stamp-apt
# three.js vendored for the view page; the stamp sits beside the files, so removing them redoes it
WEB := src/galvoscan_view/web
STAMP_WEB := src/galvoscan_view/galvoscan_view/static/vendor/.stamp-web
MSG_FILES := $(shell find msgs msgs_vendor -type f 2>/dev/null)
SRC_META := $(wildcard src/*/setup.py src/*/setup.cfg src/*/package.xml)
DEMO_OUT ?= out
PYTEST_ARGS ?=

.PHONY: setup test-deps test lint pytest explore demo results firmware clean distclean

setup: $(STAMP_SRC) $(STAMP_WEB)
	@$(PY) -c 'import rclpy, galvoscan_msgs.msg, galvoscan_msgs.srv, tf2_msgs.msg, galvoscan_common, galvoscan_sim, galvoscan_bag, galvo_driver, stripe_extractor, reconstructor, calibration_tools, galvoscan_view, galvoscan' \
	  || { echo "[setup] the venv is broken: run 'make distclean' and try again"; exit 1; }

$(STAMP_DEPS): requirements.txt constraints.txt tools/setup_venv.sh
	PYTHON=$(PYTHON) tools/setup_venv.sh deps
	@touch $@

$(STAMP_MSGS): $(STAMP_DEPS) $(MSG_FILES)
	tools/setup_venv.sh msgs
	@touch $@

$(STAMP_SRC): $(STAMP_MSGS) $(SRC_META)
	tools/setup_venv.sh src
	@touch $@

$(STAMP_WEB): $(WEB)/package.json $(WEB)/package-lock.json tools/foxglove_client/package.json \
	      tools/foxglove_client/package-lock.json tools/setup_venv.sh
	tools/setup_venv.sh web
	@touch $@

$(STAMP_APT): tools/apt-packages.txt tools/setup_venv.sh | $(STAMP_DEPS)
	tools/setup_venv.sh apt
	@touch $@

test-deps: setup $(STAMP_APT)

# gcc-avr, avr-libc and libsimavr come from tools/apt-packages.txt (the apt step)
firmware: $(STAMP_APT)
	$(MAKE) -C firmware all

lint: setup
	$(VENV)/bin/ruff check .

# pytest exits 5 when it collects no tests; that is a failure here, and says so.
pytest: test-deps firmware
	@$(PY) -m pytest $(PYTEST_ARGS); rc=$$?; \
	  if [ $$rc -eq 5 ]; then echo "ERROR: pytest collected no tests"; fi; exit $$rc

test: lint pytest

# Random hypothesis exploration (not repeatable, not part of `make test`): new examples on
# every run; whatever it finds is pinned as a deterministic test case.
explore: setup
	HYPOTHESIS_PROFILE=explore $(PY) -m pytest -m 'not dds' $(PYTEST_ARGS)

demo: setup
	$(VENV)/bin/galvoscan demo --out $(DEMO_OUT)

# Measure and rewrite docs/results/: the reference rig evaluated (the demo's job and the paper's
# method on the same rig) and the benchmarks of a minute or less, each
# recorded with its command, date, commit and machine (minutes; not part of `make test`).
# `$(PY) tools/gen_results.py --long` adds the long benchmarks (an hour or more).
results: setup
	$(PY) tools/gen_results.py

clean:
	rm -rf build $(DEMO_OUT) .pytest_cache .ruff_cache firmware/build

distclean: clean
	rm -rf $(VENV)
