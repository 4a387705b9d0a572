"""Shared fixtures. Tests that start ROS processes get a DDS domain of their own."""

from __future__ import annotations

import os
import random

import pytest

# Keep this run's DDS traffic on this host and away from other runs (CI, a developer's shell),
# and each pytest-xdist worker's away from the others' (workers inherit the first process's
# environment, so each adds its number to one base drawn once).
_DOMAIN_BASE = int(os.environ.setdefault("MOSIV_TEST_DOMAIN_BASE", str(random.Random().randint(10, 90))))
os.environ["ROS_DOMAIN_ID"] = str(_DOMAIN_BASE + int(os.environ.get("PYTEST_XDIST_WORKER", "gw0")[2:]))
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


# io fixtures


@pytest.fixture(scope="session")
def small_recording():
    """A 2-camera, 4-frame analytic recording with depth. Shared: copy it before changing it."""
    from mosiv_ros.synth.shapes import make_shapes_recording

    return make_shapes_recording(n_frames=4, n_cameras=2, width=24, height=18)


@pytest.fixture(scope="session")
def small_bag(small_recording, tmp_path_factory: pytest.TempPathFactory):
    """``small_recording`` written as an uncompressed MCAP bag. Shared: never change it."""
    from mosiv_ros.io.bag import write_recording

    return write_recording(small_recording, tmp_path_factory.mktemp("io") / "small")


# synth fixtures


@pytest.fixture(scope="session")
def synth_pair_bag(tmp_path_factory: pytest.TempPathFactory):
    """``synth_scenes.PAIR`` recorded by the synthetic recorder (seed 0). Shared: never change it."""
    from synth_scenes import PAIR, record_scene

    return record_scene(tmp_path_factory.mktemp("synth"), PAIR, "pair")


@pytest.fixture(scope="session")
def drop_bag(tmp_path_factory: pytest.TempPathFactory):
    """``synth_scenes.DROP`` recorded by the synthetic recorder. Shared: never change it."""
    from synth_scenes import DROP, record_scene

    return record_scene(tmp_path_factory.mktemp("synth"), DROP, "drop")


@pytest.fixture(scope="session")
def fast_params(tmp_path_factory: pytest.TempPathFactory):
    """A ROS 2 params file with ``synth_scenes.FAST_PARAMS``."""
    import yaml
    from synth_scenes import FAST_PARAMS

    path = tmp_path_factory.mktemp("params") / "fast.yaml"
    path.write_text(yaml.safe_dump(FAST_PARAMS))
    return path


# ros fixtures


@pytest.fixture(scope="session")
def shapes_bag(tmp_path_factory: pytest.TempPathFactory):
    """A small analytic recording (2 cameras, 8 frames at 10 fps) written as MCAP."""
    from mosiv_ros.synth.shapes import write_shapes_bag

    return write_shapes_bag(
        tmp_path_factory.mktemp("bags") / "shapes", n_frames=8, n_cameras=2, width=48, height=36
    )
