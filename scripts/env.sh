# Source this file from bash: creates or updates the project's virtual environment in .venv,
# builds the ament_python package with colcon into install/ (as `colcon build` does on a ROS 2
# Jazzy machine) and sources it, so `ros2 run`-style lookups through the ament index work.
# Re-running is fast when nothing changed: packages are installed again only when
# requirements.txt or this file change, and colcon runs only when the package files change.
_mosiv_opts=$(set +o)
set +u
_mosiv_fail() { echo "mosiv: $1" >&2; eval "$_mosiv_opts"; return 1; }
MOSIV_ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$MOSIV_ROOT" || return 1
[ -x .venv/bin/python ] || "${PYTHON:-python3}" -m venv .venv || { _mosiv_fail "cannot create .venv"; return 1; }
# shellcheck disable=SC1091
. .venv/bin/activate
_mosiv_want=$(cat requirements.txt scripts/env.sh | sha256sum | cut -d' ' -f1)
if [ "$(cat .venv/.mosiv-installed 2>/dev/null)" != "$_mosiv_want" ]; then
    echo "mosiv: installing dependencies into .venv (the first time takes a few minutes)" >&2
    # torch first and pinned: any other torch spec downloads gigabytes of CUDA packages.
    python -m pip install -q --disable-pip-version-check torch==2.13.0 2>&1 | grep -v "is ignored" >&2
    python -m pip install -q --disable-pip-version-check -r requirements.txt 2>&1 | grep -v "is ignored" >&2
    python -c "import torch, warp, rosbags, rclpy, colcon_core, pytest" \
        || { _mosiv_fail "installing the dependencies failed (see above)"; return 1; }
    echo "$_mosiv_want" > .venv/.mosiv-installed
fi
if [ ! -f install/.mosiv-built ] || [ -n "$(find setup.py setup.cfg package.xml config launch resource \
        -newer install/.mosiv-built 2>/dev/null | head -n 1)" ]; then
    colcon --log-base log build --symlink-install --event-handlers console_cohesion- >/dev/null \
        || { _mosiv_fail "colcon build failed: see log/latest_build"; return 1; }
    touch install/.mosiv-built
fi
# shellcheck disable=SC1091
. install/local_setup.sh
export PATH="$MOSIV_ROOT/install/mosiv_ros/lib/mosiv_ros:$PATH"
eval "$_mosiv_opts"
unset _mosiv_opts _mosiv_want
