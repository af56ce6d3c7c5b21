#!/usr/bin/env bash
# Builds tf2_msgs (TFMessage only) from resource/tf2_msgs with rosidl + colcon and installs it
# into a virtual environment made of the ros-jazzy-* wheels, so that `VENV/bin/python -c
# "import tf2_msgs.msg"` works in a fresh shell with nothing sourced.
#
# usage: bash resource/tf2_msgs/build_tf2_msgs.sh VENV [WORKSPACE]
#   WORKSPACE defaults to <repo>/build/tf2_msgs_ws (git-ignored).
#
# Safe to run again: it exits at once when the venv holds a build of the same sources; otherwise
# pip skips what is installed, the CMake patch only touches files that still
# name the wheel builder's paths, colcon rebuilds incrementally and the install overwrites.
set -euo pipefail

say() { printf '[tf2_msgs] %s\n' "$*"; }
die() { printf '[tf2_msgs] error: %s\n' "$*" >&2; exit 1; }

[ $# -ge 1 ] || die "usage: $0 VENV [WORKSPACE]"
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
REPO="$(cd "$HERE/../.." && pwd)"
VENV="$(cd "$1" && pwd)" || die "no venv at $1"
WS="${2:-$REPO/build/tf2_msgs_ws}"
PY="$VENV/bin/python"
[ -x "$PY" ] || die "$PY not found"
# Skip everything when this venv already holds a build of exactly these sources.
STAMP="$VENV/share/tf2_msgs/source.sha256"
DIGEST="$(cd "$HERE" && sha256sum build_tf2_msgs.sh CMakeLists.txt package.xml msg/*.msg \
    requirements-build.txt constraints-build.txt | sha256sum | cut -d' ' -f1)"
if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$DIGEST" ] && "$PY" -c 'import tf2_msgs.msg' 2>/dev/null; then
    say "up to date in $VENV (sources $DIGEST)"
    exit 0
fi

command -v cmake >/dev/null || die "cmake is not on PATH (apt-get install cmake)"
command -v c++ >/dev/null || die "no C++ compiler on PATH (apt-get install g++)"

# 1. Build-only wheels, pinned (ros-jazzy-* names only). The constraints pin what they pull in:
#    the ros-* build wheels here, and colcon's and the runtime's dependencies in requirements.txt.
say "installing build wheels from $HERE/requirements-build.txt into $VENV"
"$PY" -m pip install --quiet --disable-pip-version-check \
    -r "$HERE/requirements-build.txt" \
    -c "$HERE/constraints-build.txt" -c "$REPO/requirements.txt"

# 2. The wheels' exported CMake targets name the include dirs of the machine that built them
#    (/opt/python/cp3XX-cp3XX/...). CMake refuses imported targets with missing include dirs,
#    so point them at this interpreter's headers and the venv's numpy headers.
PY_INC="$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
NP_INC="$("$PY" -c 'import numpy; print(numpy.get_include())')"
[ -f "$PY_INC/Python.h" ] || die "Python.h not found in $PY_INC (install the python3.11 headers)"
say "patching exported CMake targets: python include -> $PY_INC, numpy include -> $NP_INC"
mapfile -t STALE < <(grep -rlE '/opt/python/[^;"]*/(include/python3|numpy/)' \
    "$VENV/share" --include='*.cmake' 2>/dev/null || true)
for f in "${STALE[@]}"; do
    sed -i -E \
        -e "s#/opt/python/[^;\"]*/site-packages/numpy/(_core|core)/include#${NP_INC}#g" \
        -e "s#/opt/python/[^;\"/]*/include/python3\.[0-9]+#${PY_INC}#g" "$f"
done
say "patched ${#STALE[@]} CMake file(s)"
if grep -rqE '/opt/python/[^;"]*/(include/python3|numpy/)' "$VENV/share" --include='*.cmake'; then
    die "some exported CMake targets still name /opt/python include dirs"
fi

# 3. colcon build in a workspace outside git. The package source is linked, not copied, so
#    edits in resource/tf2_msgs are picked up. PATH/AMENT_PREFIX_PATH/CMAKE_PREFIX_PATH make
#    the venv the underlay, as `source /opt/ros/jazzy/setup.bash` would on a ROS install.
mkdir -p "$WS/src"
ln -sfn "$HERE" "$WS/src/tf2_msgs"
say "building with colcon in $WS"
(
    cd "$WS"
    export PATH="$VENV/bin:$PATH"
    export AMENT_PREFIX_PATH="$VENV"
    export CMAKE_PREFIX_PATH="$VENV"
    export LD_LIBRARY_PATH="$VENV/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
    # The generated libraries live in VENV/lib and the Python extensions in
    # VENV/lib/python3.X/site-packages/tf2_msgs: the RPATH lets the loader find them from
    # both places even without the LD_LIBRARY_PATH that ros_wheels_bootstrapper sets.
    "$VENV/bin/colcon" build --merge-install \
        --base-paths src --build-base build --install-base install \
        --event-handlers console_direct- console_cohesion- summary+ status- \
        --cmake-args \
            -DCMAKE_BUILD_TYPE=Release -DBUILD_TESTING=OFF \
            -DPython3_EXECUTABLE="$PY" -DPython3_FIND_STRATEGY=LOCATION \
            '-DCMAKE_INSTALL_RPATH=$ORIGIN;$ORIGIN/../../..'
)

# 4. Install: the merged install tree has the venv's own layout (include/, lib/,
#    lib/python3.X/site-packages/, share/), so copy it over the venv, leaving out colcon's
#    shell setup scripts, which nothing here sources.
INSTALL="$WS/install"
[ -d "$INSTALL/lib" ] || die "colcon produced no install tree in $INSTALL"
say "installing $INSTALL into $VENV"
for d in include lib share; do
    [ -d "$INSTALL/$d" ] && cp -a "$INSTALL/$d" "$VENV/"
done
rm -rf "$VENV/share/colcon-core"
( cd "$INSTALL" && find include lib share -type f -o -type l | grep -v '^share/colcon-core/' | sort ) \
    > "$VENV/share/tf2_msgs/installed_files.txt"
say "installed $(wc -l < "$VENV/share/tf2_msgs/installed_files.txt") files (list in $VENV/share/tf2_msgs/installed_files.txt)"

echo "$DIGEST" > "$STAMP"

# 5. Check in a clean environment, as a user's fresh shell would run it.
env -i HOME="$HOME" PATH=/usr/bin:/bin "$PY" -c \
    'import tf2_msgs.msg as m, geometry_msgs.msg as g; t = m.TFMessage(transforms=[g.TransformStamped()]); print("[tf2_msgs] import ok:", type(t).__name__, len(t.transforms))'
