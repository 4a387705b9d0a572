"""Output files: the location is checked before any work, writes are whole or not at all."""

from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path

import pytest
from synth_scenes import PAIR, write_scene

from mosiv_ros.cli import main
from mosiv_ros.graph import executable_path
from mosiv_ros.identify.estimates import Estimates

UNWRITABLE = Path("/sys")  # a directory no one may create files in, root included


@pytest.mark.parametrize("command", ["run", "close-loop"])
def test_an_output_that_is_a_file_is_refused_before_the_bag_is_read(command, small_bag, tmp_path, capsys,
                                                                      caplog):
    taken = tmp_path / "taken"
    taken.write_text("not a directory")
    with caplog.at_level(logging.INFO):
        assert main([command, str(small_bag), "--out", str(taken)]) == 2
    assert f"output {taken}: is a file, not a directory" in capsys.readouterr().err
    assert not any("stage 1" in r.getMessage() or "read " in r.getMessage() for r in caplog.records)
    assert taken.read_text() == "not a directory"


@pytest.mark.skipif(not UNWRITABLE.is_dir(), reason="needs /sys (Linux)")
def test_an_output_directory_no_file_can_be_written_into_is_refused_before_any_work(small_bag, capsys, caplog):
    with caplog.at_level(logging.INFO):
        assert main(["run", str(small_bag), "--out", str(UNWRITABLE)]) == 2
    assert f"output {UNWRITABLE}: cannot write into the directory" in capsys.readouterr().err
    assert not any("stage 1" in r.getMessage() for r in caplog.records)


def test_an_output_whose_parent_is_a_file_cannot_be_created(small_bag, tmp_path, capsys):
    (tmp_path / "file").write_text("")
    out = tmp_path / "file" / "run"
    assert main(["run", str(small_bag), "--out", str(out)]) == 2
    assert f"output {out}: cannot create the directory" in capsys.readouterr().err


@pytest.mark.skipif(not UNWRITABLE.is_dir(), reason="needs /sys (Linux)")
def test_record_refuses_an_unwritable_output_before_simulating(tmp_path, capsys, caplog):
    scene = write_scene(tmp_path, PAIR)
    with caplog.at_level(logging.INFO):
        assert main(["record", str(scene), str(UNWRITABLE / "bag")]) == 2
    assert f"output {UNWRITABLE}: cannot write into the directory" in capsys.readouterr().err
    assert not any("simulating" in r.getMessage() or "laid out" in r.getMessage() for r in caplog.records)


WRITE_TWICE = """
import resource, signal, sys
from mosiv_ros.identify.estimates import Estimates, ObjectEstimate
path = sys.argv[1]
Estimates([ObjectEstimate(1, "jelly", "elastic", {"E": 2e4})], frames=6, frame_dt=0.1).write(path)
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails (EFBIG), as on a full disk
resource.setrlimit(resource.RLIMIT_FSIZE, (600, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
objects = [ObjectEstimate(k, f"object_{k}", "elastic", {"E": 3e4}) for k in range(1, 40)]
Estimates(objects, frames=6, frame_dt=0.1).write(path)
"""


def test_an_estimates_write_that_fails_half_way_leaves_the_previous_file_intact(tmp_path):
    path = tmp_path / "estimates.yaml"
    result = subprocess.run([sys.executable, "-c", WRITE_TWICE, str(path)], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode != 0 and "File too large" in result.stderr  # the second write failed
    estimates = Estimates.read(path)  # the first one is whole
    assert [o.name for o in estimates.objects] == ["jelly"] and estimates.objects[0].params == {"E": 2e4}
    assert [p.name for p in tmp_path.iterdir()] == ["estimates.yaml"]  # no temporary file left


@pytest.mark.slow
@pytest.mark.skipif(not UNWRITABLE.is_dir(), reason="needs /sys (Linux)")
@pytest.mark.parametrize(("parameter", "value", "where"), [
    ("output_yaml", str(UNWRITABLE / "estimates.yaml"), UNWRITABLE),
    ("close_loop_dir", str(UNWRITABLE / "loop"), UNWRITABLE / "loop"),
])
def test_identify_node_refuses_an_unwritable_output_when_it_starts(parameter, value, where):
    args = ["-p", f"{parameter}:={value}"] + (["-p", "close_loop:=true"] if parameter == "close_loop_dir" else [])
    result = subprocess.run([str(executable_path("identify_node")), "--ros-args", *args],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2, result.stderr
    assert f"identify_node: error: output {where}: cannot" in result.stderr
