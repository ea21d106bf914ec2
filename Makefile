# magcal_ros project tasks. `make test` is what CI runs (.ci/run).
#
#   make setup   create/update .venv (Python 3.11, ROS 2 Jazzy wheels, deps, editable install)
#   make test    setup, then pytest on test/ in the loopback-only ROS environment, in three
#                lanes (scripts/test_lanes.py): the live ROS pipelines two at a time, beside
#                them the rest on pytest-xdist workers at the idle CPU policy, and after them
#                the two pipelines that judge their own timing, one at a time
#   make demo    setup, then scripts/demo.sh in the loopback-only ROS environment
#   make bench   setup, then bench/run_all.py
#   make clean   remove build products and caches (keeps .venv); distclean also removes .venv
#
# Variables: PYTHON (a Python 3.11 for the venv, default: found on PATH), TEST_TIMEOUT (seconds per
# test, default 300), TEST_WORKERS (pytest-xdist processes of the batch lane, default 2; 0 runs it
# in one process), LIVE_WORKERS (those of the live lane, where the pipelines marked `live` in
# test/conftest.py run, default 2; 1 runs them one at a time), PYTEST_ARGS (extra pytest
# arguments, e.g. PYTEST_ARGS='-k conversions').

SHELL := /bin/bash
.DEFAULT_GOAL := test

PYTHON ?=
VENV := .venv
VPY := $(VENV)/bin/python
STAMP := $(VENV)/.magcal_setup_stamp
TEST_TIMEOUT ?= 300
TEST_WORKERS ?= 2
LIVE_WORKERS ?= 2
PYTEST_ARGS ?=
# Loopback-only DDS, per-run ROS_DOMAIN_ID, .venv/bin on PATH (see scripts/ros_env.sh).
ROS_ENV := source scripts/ros_env.sh &&

.PHONY: setup test demo bench clean distclean

setup: $(STAMP)

# Re-run only when the dependency list or the packaging changed (the stamp is written last).
$(STAMP): requirements.txt setup.py setup.cfg package.xml scripts/setup_env.sh \
		scripts/build_interfaces.sh interfaces/ros_wheels_fix.cmake \
		$(wildcard interfaces/magcal_interfaces/*/* interfaces/magcal_interfaces/*.*)
	PYTHON='$(PYTHON)' VENV='$(CURDIR)/$(VENV)' scripts/setup_env.sh

test: setup
	$(ROS_ENV) $(VPY) scripts/test_lanes.py --workers $(TEST_WORKERS) --live-workers $(LIVE_WORKERS) --timeout $(TEST_TIMEOUT) --pytest-args='$(PYTEST_ARGS)'

demo: setup
	$(ROS_ENV) scripts/demo.sh

bench: setup
	$(ROS_ENV) $(VPY) bench/run_all.py

clean:
	rm -rf build install log .pytest_cache .hypothesis *.egg-info
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -prune -exec rm -rf {} +

distclean: clean
	rm -rf $(VENV)
