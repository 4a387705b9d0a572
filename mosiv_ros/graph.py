"""The mosiv_ros node graph: what it is (``graph_nodes``), and a runner that starts it.

``graph_nodes`` is the one description of the graph: its nodes (the pipeline, then the replay) with the
parameters each gets on top of the params file. ``launch/mosiv.launch.py`` builds its launch
description from it on a ROS 2 install; ``launch`` is not installable from PyPI, so the command
line (``mosiv graph``) and the tests start the same nodes with this small runner (``Graph``),
with the same executables (found through the ament index, as ``ros2 run`` finds them) and the
same parameter file (``config/mosiv.yaml``). Each process's output is streamed line by line,
prefixed with its name, and kept for inspection.

This module starts processes; it never imports rclpy.
"""

from __future__ import annotations

import logging
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from mosiv_ros.config import PIPELINE_NODES, REPLAY_NODE

PACKAGE = "mosiv_ros"
LOG = logging.getLogger(__name__)
READY_TIMEOUT = 60.0
"""Seconds a node may take to start (import, kernel cache, DDS discovery) before it is an error."""
REPLAY_LINGER = 10.0
"""Seconds the graph's replay keeps serving its latched topics (``/tf_static``, ``/gripper/pose``)
after the bag's last message, for a node that subscribes late (identify_node and prediction_node
take the gripper's poses from it)."""
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
"""Signals on which the runner stops its nodes before it ends."""


class GraphError(RuntimeError):
    """A node process could not be found, started or stopped, or failed while running."""


class NodeExited(GraphError):
    """A node process exited while something was waiting for it."""


class NodeFailed(GraphError):
    """A node process reported a failure while something was waiting for it."""


class Stopped(GraphError):
    """The runner got SIGINT, SIGTERM or SIGHUP while its graph ran."""


def exit_description(code: int) -> str:
    """'exited with code 2', or 'was killed by SIGABRT' for a process a signal ended."""
    if code < 0:
        try:
            return f"was killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"was killed by signal {-code}"
    return f"exited with code {code}"


MAX_DOMAIN_ID = 232
"""The largest ROS domain id (ROS 2 documentation: the DDS port range caps it)."""
DOMAIN_IDS = range(1, 102)
"""ROS domain ids a graph gets by default: 0 is every shell's default, and above 101 a
participant's DDS ports can reach the ephemeral ports on Linux."""
DOMAIN_PORTS = (7400, 250)
"""The DDS (RTPS) port mapping: domain d uses UDP ports base + gain * d up to the next domain's."""


def domains_in_use(udp_tables: Sequence[str | Path] = ("/proc/net/udp", "/proc/net/udp6")) -> set[int]:
    """The ROS domains that have a DDS participant on this host: those whose UDP ports are bound.

    Read from the kernel's socket tables (Linux); none where they cannot be read.
    """
    base, gain = DOMAIN_PORTS
    used = set()
    for table in udp_tables:
        try:
            rows = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for row in rows:
            port = int(row.split()[1].rsplit(":", 1)[1], 16)  # local_address is HEXIP:HEXPORT
            if port >= base:
                used.add((port - base) // gain)
    return used


def free_domain_id() -> int:
    """A ROS domain id of DOMAIN_IDS that no DDS participant on this host uses; GraphError if none.

    One at random: two graphs started at once should not both take the lowest.
    """
    free = sorted(set(DOMAIN_IDS) - domains_in_use())
    if not free:
        raise GraphError(f"every ROS domain {DOMAIN_IDS.start}..{DOMAIN_IDS.stop - 1} has a DDS "
                         "participant on this host; choose one with --domain-id")
    return random.choice(free)


def package_prefix() -> Path:
    """The install prefix of mosiv_ros, from the ament index (as ``ros2 run`` finds it)."""
    from ament_index_python.packages import PackageNotFoundError, get_package_prefix

    try:
        return Path(get_package_prefix(PACKAGE))
    except (PackageNotFoundError, OSError) as error:
        raise GraphError(
            f"package '{PACKAGE}' is not in the ament index ({error}); build it with "
            "`colcon build` and source install/setup.bash (here: `. scripts/env.sh`)"
        ) from error


def executable_path(name: str) -> Path:
    """``<prefix>/lib/mosiv_ros/<name>``: the file ``ros2 run mosiv_ros <name>`` executes."""
    path = package_prefix() / "lib" / PACKAGE / name
    if not os.access(path, os.X_OK):
        raise GraphError(f"no executable '{name}' at {path}")
    return path


def default_params_file() -> Path:
    """The installed ``share/mosiv_ros/config/mosiv.yaml``."""
    return package_prefix() / "share" / PACKAGE / "config" / "mosiv.yaml"


@dataclass
class NodeSpec:
    """One node process: its executable and the parameters that override the params file."""

    executable: str
    parameters: dict[str, Any] = field(default_factory=dict)


def graph_nodes(bag: Any, rate: Any, scene: Any,
                overrides: dict[str, dict[str, Any]] | None = None) -> list[NodeSpec]:
    """The mosiv graph: the pipeline nodes with ``scene``, then the replay of ``bag``.

    The replay waits until every image topic has a subscriber and replays at ``rate``;
    ``overrides`` adds parameters by pipeline node. The values may be of any kind a caller passes on:
    the launch file gives its launch arguments (substitutions).
    """
    overrides = overrides or {}
    specs = [NodeSpec(name, {"scene": scene, **overrides.get(name, {})}) for name in PIPELINE_NODES]
    # the camera topics are volatile: the replay holds its first message until they have a
    # subscriber (reconstruction_node subscribes once it sees them), as long as a node may take to
    # start; the pipeline's own topics are transient_local, so a node may come up later
    specs.append(NodeSpec(REPLAY_NODE, {"bag": bag, "rate": rate, "wait_for_subscribers": 1,
                                        "wait_timeout": READY_TIMEOUT, "linger": REPLAY_LINGER}))
    return specs


def print_line(line: str) -> None:
    """Print one line to stdout in one write: the reader threads of several nodes share it."""
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


class NodeProcess:
    """A running node: its process, and the output lines it has printed so far."""

    def __init__(self, spec: NodeSpec, argv: list[str], env: dict[str, str],
                 sink: Callable[[str], None] | None) -> None:
        self.name = spec.executable
        self.lines: list[str] = []
        self._sink = sink
        self._new_line = threading.Condition()
        self.process = subprocess.Popen(
            argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL, text=True, bufsize=1, start_new_session=True,
        )
        self._reader = threading.Thread(target=self._pump, name=f"out-{self.name}", daemon=True)
        self._reader.start()

    def _pump(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            line = line.rstrip("\n")
            with self._new_line:
                self.lines.append(line)
                self._new_line.notify_all()
            if self._sink is not None:
                self._sink(f"[{self.name}] {line}")

    def wait_for_line(self, text: str, timeout: float,
                      check: Callable[[], None] | None = None, failures: Sequence[str] = ()) -> str:
        """Block until the process prints a line containing ``text``; return that line.

        Raises ``NodeExited`` as soon as the process has exited without printing it, ``NodeFailed``
        as soon as it prints a line containing one of ``failures`` (what it says when the awaited
        line will not come), and ``GraphError`` when ``timeout`` seconds pass; ``check`` (called a
        few times a second) may raise to stop the wait early, e.g. when another node of the graph
        has failed.
        """
        began = time.monotonic()
        deadline = began + timeout
        seen = 0
        with self._new_line:
            while True:
                for line in self.lines[seen:]:
                    if text in line:
                        return line
                    if any(failure in line for failure in failures):
                        raise NodeFailed(f"{self.name} failed before printing a line containing "
                                         f"{text!r}: {line}")
                seen = len(self.lines)
                if self.process.poll() is not None and not self._reader.is_alive():
                    raise NodeExited(
                        f"{self.name} {exit_description(self.process.returncode)} before printing "
                        f"a line containing {text!r} (waited {time.monotonic() - began:.0f} s); "
                        "last lines:\n" + self.tail())
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise GraphError(
                        f"{self.name} printed no line containing {text!r} within {timeout:.0f} s "
                        "and is still running; last lines:\n" + self.tail())
                if check is not None:
                    check()
                self._new_line.wait(min(remaining, 0.2))

    def tail(self, n: int = 20) -> str:
        """The last ``n`` lines the process printed."""
        return "\n".join(self.lines[-n:])

    def wait_ready(self, timeout: float) -> bool:
        """Wait for the node's '<name> ready' line: True, or False if it exited first."""
        try:
            self.wait_for_line(f"{self.name} ready", timeout)
            return True
        except NodeExited:
            return False

    def stop(self, timeout: float) -> int:
        """SIGINT (a clean rclpy shutdown), then SIGTERM, then SIGKILL; return the exit code."""
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            if self.process.poll() is not None:
                break
            try:
                os.killpg(self.process.pid, sig)
            except ProcessLookupError:
                break
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                LOG.warning("%s did not stop on %s", self.name, signal.Signals(sig).name)
        self._reader.join(timeout)
        return self.process.wait()


class Graph:
    """Node processes with one params file, started side by side; stopped in reverse order."""

    def __init__(
        self,
        specs: list[NodeSpec],
        *,
        params_file: Path | None = None,
        env: dict[str, str] | None = None,
        sink: Callable[[str], None] | None = print_line,
    ) -> None:
        self.specs = specs
        self.params_file = Path(params_file) if params_file else default_params_file()
        self.env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
        self.sink = sink
        self.nodes: dict[str, NodeProcess] = {}
        self._handlers: dict[int, Any] = {}  # the signal handlers before start
        self._tmp = tempfile.TemporaryDirectory(prefix="mosiv-graph-")
        self.env.setdefault("ROS_LOG_DIR", self._tmp.name)

    def argv(self, spec: NodeSpec) -> list[str]:
        """The command line of one node: ``--ros-args --params-file`` defaults, then overrides."""
        argv = [str(executable_path(spec.executable)), "--ros-args",
                "--params-file", str(self.params_file)]
        if spec.parameters:
            overrides = Path(self._tmp.name) / f"{spec.executable}.yaml"
            overrides.write_text(yaml.safe_dump(
                {spec.executable: {"ros__parameters": spec.parameters}}))
            argv += ["--params-file", str(overrides)]
        return argv

    def start(self) -> Graph:
        """Start the nodes; on any failure or signal on the way, stop those started.

        They start side by side (their imports share the cores), then each is waited for
        (``graph_nodes`` says why no node misses a message). A node that exits at start-up is
        left for the caller to see.
        """
        if not self.params_file.is_file():
            raise GraphError(f"params file {self.params_file} does not exist")
        self._catch_signals()
        try:
            for spec in self.specs:
                self.nodes[spec.executable] = NodeProcess(spec, self.argv(spec), self.env, self.sink)
            for node in self.nodes.values():
                node.wait_ready(READY_TIMEOUT)
        except BaseException:
            self.stop()
            raise
        return self

    def _catch_signals(self) -> None:
        """Make SIGINT, SIGTERM and SIGHUP raise ``Stopped`` while the graph runs (main thread only).

        The nodes run in sessions of their own (a Ctrl-C in the terminal reaches the runner
        alone, which then stops them in order): were the runner to die of a signal, they would
        keep running. The exception ends the caller's wait, and its ``with`` block stops them.
        """
        if threading.current_thread() is not threading.main_thread():
            return

        def stopped(signum: int, _frame: object) -> None:
            self._ignore_signals()  # once: a second signal must not cut the stopping short
            raise Stopped(f"got {signal.Signals(signum).name}; stopping the nodes")

        for sig in STOP_SIGNALS:
            self._handlers[sig] = signal.signal(sig, stopped)

    def _ignore_signals(self) -> None:
        for sig in self._handlers:
            signal.signal(sig, lambda _signum, _frame: None)

    def wait_for_line(self, name: str, text: str, timeout: float, failures: Sequence[str] = ()) -> str:
        """``NodeProcess.wait_for_line`` on node ``name``, also stopped by another node's failure.

        The wait ends, with the reason, as soon as node ``name`` prints one of ``failures`` or any
        other node of the graph exits with a code other than 0.
        """

        def others_alive() -> None:
            for other, node in self.nodes.items():
                code = node.process.poll()
                if other != name and code not in (None, 0):
                    raise NodeExited(f"{other} {exit_description(code)} while waiting for {name} "
                                     f"to print {text!r}; its last lines:\n" + node.tail())

        return self.nodes[name].wait_for_line(text, timeout, others_alive, failures)

    def stop(self, timeout: float = 5.0) -> dict[str, int]:
        """Stop every node, last started first; return their exit codes.

        Signals that ``start`` caught are ignored until the nodes are stopped, then handled as
        before it.
        """
        self._ignore_signals()
        try:
            codes = {name: node.stop(timeout) for name, node in reversed(self.nodes.items())}
        finally:
            for sig, handler in self._handlers.items():
                signal.signal(sig, handler)
            self._handlers = {}
        self._tmp.cleanup()
        return codes

    def __enter__(self) -> Graph:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

