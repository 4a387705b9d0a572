"""`mosiv graph` as a process: the ROS domain it gives its nodes, its end when a node fails, and
its nodes when it gets a signal."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mosiv_ros.cli import graph_domain
from mosiv_ros.graph import DOMAIN_IDS, DOMAIN_PORTS, domains_in_use, free_domain_id
from mosiv_ros.io.bag import read_recording, write_recording


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (Linux /proc)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found


def _environ(pid: int) -> dict[str, str]:
    pairs = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    return dict(p.decode().split("=", 1) for p in pairs if b"=" in p)


def _graph(bag: Path, params: Path, out: Path, *options: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "mosiv_ros", "graph", str(bag), "--rate", "1",
                             "--params-file", str(params), "--out", str(out), *options],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def test_a_free_domain_is_one_no_participant_on_this_host_has_bound_a_port_of():
    base, gain = DOMAIN_PORTS
    taken = free_domain_id()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", base + gain * taken + 11))  # a participant's unicast port
        assert taken in domains_in_use()
        assert all(free_domain_id() != taken for _ in range(200))
    assert all(d in DOMAIN_IDS for d in (free_domain_id() for _ in range(50)))
    env, line = graph_domain("17", {"ROS_DOMAIN_ID": "3"})
    assert env == {"ROS_DOMAIN_ID": "17"} and line.startswith("ROS domain 17 (chosen with --domain-id)")
    env, line = graph_domain("env", {"ROS_DOMAIN_ID": "3", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"})
    assert env == {} and line == ("ROS domain 3 (the environment's, chosen with --domain-id env), "
                                  "discovery range LOCALHOST")
    with pytest.raises(ValueError, match="--domain-id: expected auto, env or a domain id 0..232, got '300'"):
        graph_domain("300", {})


@pytest.mark.slow
def test_mosiv_graph_on_sigterm_stops_every_node_in_its_own_free_domain(drop_bag, fast_params, tmp_path):
    runner = _graph(drop_bag, fast_params, tmp_path / "graph")
    children: list[int] = []
    try:
        first = runner.stdout.readline()
        lines = [first]
        for line in runner.stdout:
            lines.append(line)
            if "bag_replay_node ready" in line:  # the fifth and last node is up
                break
        children = _children(runner.pid)  # the nodes, and the kernels' builder if it still runs
        nodes = [pid for pid in children if b"/lib/mosiv_ros/" in Path(f"/proc/{pid}/cmdline").read_bytes()]
        environ = [_environ(pid) for pid in nodes]
        runner.send_signal(signal.SIGTERM)  # as `timeout`, a supervisor or `kill` sends it
        runner.wait(60)
        lines += runner.stdout.readlines()
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and any(Path(f"/proc/{pid}").exists() for pid in children):
            time.sleep(0.1)
        left = [pid for pid in children if Path(f"/proc/{pid}").exists()]
    finally:
        for pid in children:  # never leave a node behind, whatever happened above
            try:
                os.killpg(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        runner.kill()
    output = "".join(lines)
    assert len(nodes) == 5 and len(children) - len(nodes) <= 1, output[-3000:]
    assert not left, f"processes still running after the runner ended: {left}\n" + output[-3000:]
    assert runner.returncode == 1 and "the graph did not finish: got SIGTERM; stopping the nodes" in output
    # an isolated domain by default, said first: no other graph's messages leak in
    assert first.startswith("mosiv graph: ROS domain ") and first.rstrip().endswith(
        "(a free one, chosen with --domain-id auto), discovery range LOCALHOST"), first
    domain = first.split()[4]
    assert {e["ROS_DOMAIN_ID"] for e in environ} == {domain}
    assert {e["ROS_AUTOMATIC_DISCOVERY_RANGE"] for e in environ} == {"LOCALHOST"}


@pytest.mark.slow
def test_mosiv_graph_ends_as_soon_as_identification_reports_failure(drop_bag, fast_params, tmp_path):
    recording = read_recording(drop_bag)
    for camera in recording.cameras.values():  # frame 3 taken 40 ms late: no frame time fits
        camera.frames[3].stamp_ns += 40_000_000
    bag = write_recording(recording, tmp_path / "uneven")
    runner = _graph(bag, fast_params, tmp_path / "graph")
    try:
        output, _ = runner.communicate(timeout=500)
    finally:
        runner.kill()
    assert runner.returncode == 1, output[-3000:]
    # it then waited 120 s for prediction_node, which had said "estimates unusable; no prediction"
    assert ("the graph did not finish: identify_node failed before printing a line containing "
            "'identification done'") in output, output[-3000:]
    assert "identification failed: observed frames are not evenly spaced" in output
