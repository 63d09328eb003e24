#!/bin/bash
# Build one interface package (dc_interfaces, dc_lifecycle_interfaces, tf2_msgs) with plain cmake and install it
# into the venv prefix, or restore the same install tree from the interface cache (called by the Makefile).
#
#   install-interfaces.sh [--archive] SOURCE_DIR VENV BUILD_ROOT CACHE_DIR KEY_FILE...
#
# --archive only prints where the build of these inputs is (or would be) cached.
#
# The cmake build is most of a fresh clone's install time (about 20 s per package on an idle 2-core machine,
# minutes under load), and its result depends only on the package's sources, the ROS wheels it is built against,
# Python, cmake and the compiler. So each install tree is kept in CACHE_DIR under a hash of those, and a second
# clone on the same machine unpacks it instead of building (CACHE_DIR empty: always build). The tree is relocatable
# (no RPATH; the ROS libraries are found through the wheels' LD_LIBRARY_PATH) except for two text files per
# package that name the prefix: their prefix is rewritten on restore.
#
# Either way, what the previous install of this package put into the venv (build/NAME/install_manifest.txt) is
# removed first: a type taken out of a package must leave no generated file behind.
set -euo pipefail

print_archive=false
if [ "$1" = --archive ]; then
	print_archive=true
	shift
fi
src=$1 venv=$2 build_root=$3 cache=$4
shift 4
name=$(basename "$src")
vpy=$venv/bin/python
build=$build_root/$name
manifest=$build/install_manifest.txt

unset AMENT_PREFIX_PATH CMAKE_PREFIX_PATH COLCON_PREFIX_PATH PYTHONPATH
# Only this venv's ROS libraries, computed from a clean environment.
LD_LIBRARY_PATH="$(env -u LD_LIBRARY_PATH "$vpy" -c 'import ros_wheels_bootstrapper as b; print(b.get_ros_paths())')"
export LD_LIBRARY_PATH

remove_previous_install() {
	if [ -f "$manifest" ]; then
		{ grep -F "$venv/" "$manifest" || true; } | xargs -r -d '\n' rm -f
	fi
	rm -rf "$build"
}

key=$(
	{
		# the package's sources and the given files (the shared cmake include, this script)
		find "$src" -type f -print0 | LC_ALL=C sort -z | xargs -0 sha256sum | sed "s|  $src/|  |"
		sha256sum "$@" | awk '{print $1}'
		# what it is built against: the ROS wheels and NumPy in the venv, by name and version (not the whole
		# constraints file: a pin added for a test extra must not cost every clone a rebuild)
		find "$venv"/lib/python3*/site-packages -maxdepth 1 \( -name 'ros_*.dist-info' -o -name 'numpy-*.dist-info' \) \
			-printf '%f\n' | LC_ALL=C sort
		"$vpy" -c 'import sys, platform; print(sys.version, platform.machine())'
		cmake --version | head -n 1
		c++ --version | head -n 1
	} | sha256sum | cut -c1-24
)
archive=${cache:+$cache/$name-$key.tar}
if $print_archive; then
	echo "$archive"
	exit 0
fi

if [ -n "$archive" ] && [ -f "$archive" ]; then
	echo "$name: unpacking the build cached in $archive (same sources, ROS wheels, Python, cmake and compiler)"
	remove_previous_install
	mkdir -p "$build"
	tar -xf "$archive" -C "$venv" --exclude=./.dc-prefix
	old_prefix=$(tar -xOf "$archive" ./.dc-prefix)
	tar -tf "$archive" | grep -v -e '/$' -e '^\./\.dc-prefix$' | sed "s|^\./|$venv/|" >"$manifest"
	xargs -r -d '\n' grep -lIF -- "$old_prefix" <"$manifest" | xargs -r -d '\n' sed -i "s|$old_prefix|$venv|g"
	exit 0
fi

remove_previous_install
cmake -S "$src" -B "$build" \
	-DCMAKE_PREFIX_PATH="$venv" -DCMAKE_INSTALL_PREFIX="$venv" \
	-DPython3_EXECUTABLE="$vpy" -DCMAKE_BUILD_TYPE=Release -DBUILD_TESTING=OFF
cmake --build "$build" -j "$(nproc 2>/dev/null || echo 2)"
cmake --install "$build"

if [ -n "$archive" ]; then
	# Written beside the final name and renamed: a clone building the same package at the same time, or an
	# interrupted build, never leaves a partial archive under the final name.
	mkdir -p "$cache"
	tmp=$(mktemp "$archive.XXXXXX")
	printf '%s' "$venv" >"$build/.dc-prefix"
	tar -cf "$tmp" -C "$venv" --files-from <(grep -F "$venv/" "$manifest" | sed "s|^$venv/|./|")
	tar -rf "$tmp" -C "$build" ./.dc-prefix
	mv "$tmp" "$archive"
	echo "$name: build cached in $archive"
fi
