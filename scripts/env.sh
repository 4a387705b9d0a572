# Source this file from bash: creates or updates the project's virtual environment in .venv,
# builds the ament_python package with colcon into install/ (as `colcon build` does on a ROS 2
# Jazzy machine) and sources it, so `ros2 run`-style lookups through the ament index work.
# Re-running is fast when nothing changed: packages are installed again only when
# requirements.txt or this file change, and colcon runs only when the package files change.
_mosiv_opts=$(set +o)
set +u
_mosiv_fail() { echo "mosiv: $1" >&2; eval "$_mosiv_opts"; return 1; }
# pip, quiet, without the index's "Location ... is ignored" noise; fails when pip fails.
_mosiv_pip() {
    python -m pip install -q --disable-pip-version-check "$@" 2>&1 \
        | { grep -v "is ignored: it is neither a file nor a directory" || true; } >&2
    return "${PIPESTATUS[0]}"
}
MOSIV_ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$MOSIV_ROOT" || return 1
[ -x .venv/bin/python ] || "${PYTHON:-python3}" -m venv .venv || { _mosiv_fail "cannot create .venv"; return 1; }
# shellcheck disable=SC1091
. .venv/bin/activate
_mosiv_want=$(cat requirements.txt scripts/env.sh | sha256sum | cut -d' ' -f1)
if [ "$(cat .venv/.mosiv-installed 2>/dev/null)" != "$_mosiv_want" ]; then
    echo "mosiv: installing dependencies into .venv (the first time takes a few minutes)" >&2
    # torch first and pinned: any other torch spec downloads gigabytes of CUDA packages.
    { _mosiv_pip torch==2.13.0 && _mosiv_pip -r requirements.txt \
        && python -c "import torch, warp, rosbags, rclpy, colcon_core, pytest"; } \
        || { _mosiv_fail "installing the dependencies failed (see above)"; return 1; }
    echo "$_mosiv_want" > .venv/.mosiv-installed
fi
# The PyPI wheels carry common_interfaces but not geometry2's tf2_msgs (/tf_static): build the
# TFMessage interface into the venv prefix with ament_cmake, once (a ROS 2 install already has it).
if ! python -c "import tf2_msgs.msg" 2>/dev/null; then
    echo "mosiv: building tf2_msgs into .venv" >&2
    _mosiv_v="$MOSIV_ROOT/.venv"
    rm -rf build/tf2_msgs && mkdir -p build
    { AMENT_PREFIX_PATH="$_mosiv_v" cmake -S scripts/ros_overlay/tf2_msgs -B build/tf2_msgs \
        -DCMAKE_PREFIX_PATH="$_mosiv_v" -DCMAKE_INSTALL_PREFIX="$_mosiv_v" \
        -DPython3_EXECUTABLE="$_mosiv_v/bin/python" -DBUILD_TESTING=OFF \
        && cmake --build build/tf2_msgs -j 2 && cmake --install build/tf2_msgs; } >build/tf2_msgs.log 2>&1 \
        && python -c "import tf2_msgs.msg" \
        || { _mosiv_fail "building tf2_msgs failed: see build/tf2_msgs.log"; return 1; }
fi
if [ ! -f install/.mosiv-built ] || [ -n "$(find setup.py setup.cfg package.xml config launch resource \
        -newer install/.mosiv-built 2>/dev/null | head -n 1)" ]; then
    colcon --log-base log build --symlink-install >/dev/null \
        || { _mosiv_fail "colcon build failed: see log/latest_build"; return 1; }
    touch install/.mosiv-built
fi
# shellcheck disable=SC1091
. install/local_setup.sh
export PATH="$MOSIV_ROOT/install/mosiv_ros/lib/mosiv_ros:$PATH"
eval "$_mosiv_opts"
unset _mosiv_opts _mosiv_want _mosiv_v
unset -f _mosiv_pip
