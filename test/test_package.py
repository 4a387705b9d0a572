"""The ament_python package contract that `ros2 run mosiv_ros <node>` relies on."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml
from ament_index_python.packages import get_package_prefix, get_package_share_directory

from mosiv_ros.cli import default_parameters_yaml, load_params_file
from mosiv_ros.config import STAGE_CONFIGS, describe, flat, value_of
from mosiv_ros.graph import REPLAY_NODE, Graph, NodeExited, NodeSpec, exit_description, graph_nodes

ROOT = Path(__file__).resolve().parents[1]
NODES = sorted(STAGE_CONFIGS)
MSG_DEPENDENCIES = {"rclpy", "sensor_msgs", "geometry_msgs", "nav_msgs", "visualization_msgs",
                    "diagnostic_msgs", "tf2_msgs", "std_msgs"}


def test_ament_index_finds_package_xml_and_every_node_executable():
    prefix = Path(get_package_prefix("mosiv_ros"))
    share = Path(get_package_share_directory("mosiv_ros"))
    assert share == prefix / "share" / "mosiv_ros"
    manifest = ET.parse(share / "package.xml").getroot()
    assert manifest.findtext("name") == "mosiv_ros"
    assert set(NODES) == {"bag_replay_node", "reconstruction_node", "lifting_node",
                          "identify_node", "prediction_node"}
    for node in NODES:
        executable = prefix / "lib" / "mosiv_ros" / node
        assert executable.is_file() and os.access(executable, os.X_OK), executable
    assert (share / "config" / "mosiv.yaml").is_file()
    assert (share / "launch" / "mosiv.launch.py").is_file()


def test_package_xml_is_format3_ament_python_with_the_message_dependencies():
    manifest = ET.parse(ROOT / "package.xml").getroot()
    assert manifest.get("format") == "3"
    assert manifest.find("export/build_type").text == "ament_python"
    depends = {e.text for e in manifest if e.tag in ("depend", "exec_depend")}
    assert MSG_DEPENDENCIES <= depends


@pytest.mark.slow
def test_node_help_lists_every_parameter_with_its_default():
    exe = Path(get_package_prefix("mosiv_ros")) / "lib" / "mosiv_ros" / "identify_node"
    out = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    for name, default, _ in describe(STAGE_CONFIGS["identify_node"]):
        assert f"  {name} (default {default!r})" in out.stdout


@pytest.mark.slow
def test_node_starts_and_stops_cleanly_on_sigint():
    with Graph([NodeSpec("prediction_node")], sink=None) as graph:
        node = graph.nodes["prediction_node"]
        node.wait_for_line("prediction_node ready", timeout=60)
        assert node.process.poll() is None
        codes = graph.stop()
    assert codes == {"prediction_node": 0}


@pytest.mark.slow
def test_bad_parameter_value_stops_the_node_with_a_clear_error(tmp_path):
    with Graph([NodeSpec("bag_replay_node", {"bag": str(tmp_path / "nope")})], sink=None) as graph:
        node = graph.nodes["bag_replay_node"]
        assert node.process.wait(60) == 2
        node.wait_for_line("nope", timeout=5)


@pytest.mark.slow
def test_a_wait_on_the_graph_ends_as_soon_as_a_node_exits_and_says_how(tmp_path):
    specs = [NodeSpec("prediction_node"), NodeSpec("bag_replay_node", {"bag": str(tmp_path / "nope")})]
    with Graph(specs, sink=None) as graph:
        replay = graph.nodes["bag_replay_node"]
        replay.process.wait(60)
        began = time.monotonic()
        with pytest.raises(NodeExited, match=r"bag_replay_node exited with code 2 before printing a "
                                             r"line containing 'replayed' \(waited 0 s\)"):
            replay.wait_for_line("replayed", timeout=600)
        with pytest.raises(NodeExited, match="bag_replay_node exited with code 2 while waiting for "
                                             "prediction_node to print 'predicted'"):
            graph.wait_for_line("prediction_node", "predicted", timeout=600)
        assert time.monotonic() - began < 5  # not the timeout
    assert exit_description(-6) == "was killed by SIGABRT" and exit_description(0) == "exited with code 0"


def test_params_file_equals_the_config_defaults():
    assert (ROOT / "config" / "mosiv.yaml").read_text() == default_parameters_yaml()
    document = yaml.safe_load(default_parameters_yaml())
    assert set(document) == set(NODES)
    for node, config in STAGE_CONFIGS.items():
        params = flat(document[node]["ros__parameters"])  # groups nest: search: {samples: 32}
        assert list(params) == [name for name, _, _ in describe(config)]
        for name, default, help_text in describe(config):
            assert params[name] == default and type(params[name]) is type(default)
            assert help_text, f"{node}.{name} has no description"


def test_a_params_file_value_out_of_its_range_is_refused_naming_the_parameter(tmp_path):
    for node, name, value, message in [
        ("prediction_node", "horizon", 1.0e9, "horizon: 1000000000.0 is out of range \\[0, 60\\]"),
        ("prediction_node", "frame_rate", 0.0, "frame_rate: 0.0 is out of range \\[0.1, 1000\\]"),
        ("identify_node", "curriculum", {"horizons": [5, -1, 0]}, "curriculum.horizons: -1 is out of range"),
        ("lifting_node", "particle_spacing", float("nan"), "particle_spacing: nan is out of range"),
        ("reconstruction_node", "voxel_size", "fine", "voxel_size: expected a number, got 'fine'"),
    ]:
        path = tmp_path / "params.yaml"
        path.write_text(yaml.safe_dump({node: {"ros__parameters": {name: value}}}))
        with pytest.raises(ValueError, match=message):
            load_params_file(path)


@pytest.mark.parametrize("path", sorted((ROOT / "config").glob("*.yaml")), ids=lambda p: p.name)
def test_every_shipped_params_file_names_known_nodes_and_parameters_of_their_types(path):
    configs = load_params_file(path)  # unknown nodes or parameters are refused
    document = yaml.safe_load(path.read_text())
    for node, section in document.items():
        for name, value in flat(section["ros__parameters"]).items():
            default = value_of(STAGE_CONFIGS[node](), name)
            assert type(value) is type(default), (node, name, value)
            assert value_of(configs[node], name) == value


def test_the_graph_gives_every_node_parameters_it_has_and_starts_every_node_once():
    specs = graph_nodes("/bag", 1.0, "/bag", {"identify_node": {"window": 5}})
    assert sorted(s.executable for s in specs) == NODES
    for spec in specs:
        assert set(spec.parameters) <= {name for name, _, _ in describe(STAGE_CONFIGS[spec.executable])}
    assert specs[-1].executable == REPLAY_NODE  # once the pipeline listens


def test_launch_file_launches_the_graph_of_graph_py():
    # launch_ros first: with the repository on sys.path, "launch" alone finds its launch/ folder
    launch_ros = pytest.importorskip("launch_ros", reason="launch is not installed (no ROS 2 install)")
    import launch
    loader = importlib.util.spec_from_file_location("mosiv_launch", ROOT / "launch" / "mosiv.launch.py")
    module = importlib.util.module_from_spec(loader)
    loader.loader.exec_module(module)
    description = module.generate_launch_description()
    nodes = [e for e in description.entities if isinstance(e, launch_ros.actions.Node)]
    assert [n.node_executable for n in nodes] == [s.executable for s in graph_nodes("", 1.0, "")]
    assert all(n.condition is None for n in nodes[:-1])
    context = launch.LaunchContext()
    for bag, replayed in (("", False), ("/some/bag", True)):
        context.launch_configurations["bag"] = bag
        assert nodes[-1].condition.evaluate(context) is replayed


@pytest.mark.parametrize("marker", ["resource/mosiv_ros"])
def test_setup_installs_the_ament_marker_and_scripts_to_lib(marker):
    setup_cfg = (ROOT / "setup.cfg").read_text()
    assert "install_scripts=$base/lib/mosiv_ros" in setup_cfg
    assert "script_dir=$base/lib/mosiv_ros" in setup_cfg
    assert (ROOT / marker).is_file()
