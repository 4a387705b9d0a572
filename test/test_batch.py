"""``mosiv batch``: recordings found under directories, run as Ray tasks, resumed, summed up."""

from __future__ import annotations

import copy
import json
import shutil

import pytest
import yaml

from mosiv_ros.batch import (
    LOG_FILE,
    SUMMARY,
    Item,
    _slots,
    aggregate,
    find_items,
    markdown,
    process,
    scale_error,
    summarise,
    task_resources,
)
from mosiv_ros.cli import main
from mosiv_ros.io.errors import BagError
from mosiv_ros.loop.truth import judge
from mosiv_ros.prepare import RunConfig


def _bag(path):
    path.mkdir(parents=True)
    (path / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    return path


def test_recordings_are_found_at_any_depth_and_named_by_their_path_below_the_directory(tmp_path):
    _bag(tmp_path / "lab" / "robot1" / "take")
    _bag(tmp_path / "lab" / "robot2" / "take")
    _bag(tmp_path / "lab" / "single")
    (tmp_path / "lab" / "notes").mkdir()
    alone = _bag(tmp_path / "elsewhere" / "alone")
    items = find_items([tmp_path / "lab", alone])
    assert [i.name for i in items] == ["robot1__take", "robot2__take", "single", "alone"]
    assert items[0].bag == tmp_path / "lab" / "robot1" / "take"


def test_two_recordings_that_would_share_a_folder_and_a_path_without_bags_are_refused(tmp_path):
    first, second = _bag(tmp_path / "a" / "take"), _bag(tmp_path / "b" / "take")
    with pytest.raises(ValueError, match="would share the folder 'take'"):
        find_items([first, second])
    assert [i.name for i in find_items([first, first])] == ["take"]
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagError, match="holds no rosbag2 directory"):
        find_items([tmp_path / "empty"])
    with pytest.raises(BagError, match="does not exist"):
        find_items([tmp_path / "missing"])


def test_a_task_asks_for_one_gpu_on_cuda_else_for_the_cores_its_fit_uses():
    config = RunConfig()
    config.identify.device = "auto"
    assert task_resources(config, {"CPU": 16, "GPU": 2}) == ({"num_gpus": 1, "num_cpus": 1}, "cuda:0")
    assert task_resources(config, {"CPU": 16}) == ({"num_cpus": 1}, "cpu")
    config.identify.device, config.identify.cpu_workers = "cpu", 4
    assert task_resources(config, {"CPU": 16, "GPU": 2}) == ({"num_cpus": 4}, "cpu")
    with pytest.raises(ValueError, match="only 2 CPU cores"):
        task_resources(config, {"CPU": 2})
    config.identify.device = "cuda:1"
    with pytest.raises(ValueError, match="has no GPU"):
        task_resources(config, {"CPU": 16})


def test_recordings_can_share_a_gpu_and_as_many_run_at_once_as_the_shares_fit():
    config = RunConfig()
    config.identify.device = "cuda:0"
    for per_gpu, gpus, running in ((1, 2, 2), (3, 1, 3), (4, 2, 8)):
        resources, device = task_resources(config, {"CPU": 16, "GPU": gpus}, per_gpu)
        assert resources == {"num_gpus": 1 / per_gpu, "num_cpus": 1} and device == "cuda:0"
        assert _slots(resources, {"CPU": 16, "GPU": gpus}) == running


def _entry(name, pair, cd, emd, dex=None, outcome=None):
    entry = {"recording": name, "status": "done", "pair": pair, "scale_error_dex": dex,
             "scores": {"observed": {"cd": cd[0], "emd": emd[0]}, "future": {"cd": cd[1], "emd": emd[1]}}}
    if outcome:
        entry["loop"] = {"outcome": outcome}
    return entry


def test_the_suite_table_averages_each_score_per_material_pair_and_over_all_finished_recordings():
    entries = [_entry("a", "elastic / sand", (0.002, 0.006), (0.01, 0.03), 0.5, "right"),
               _entry("b", "elastic / sand", (0.004, 0.010), (0.02, 0.05), 0.1, "missed"),
               _entry("c", "fluid / fluid", (0.003, 0.005), (0.04, 0.07)),
               {"recording": "d", "status": "failed", "error": "BagError: truncated"}]
    table = aggregate(entries)
    assert list(table) == ["elastic / sand", "fluid / fluid", "all"]
    sand = table["elastic / sand"]
    assert sand["recordings"] == 2
    assert sand["cd_observed"] == pytest.approx(0.003) and sand["cd_future"] == pytest.approx(0.008)
    assert sand["emd_future"] == pytest.approx(0.04) and sand["cd_truth_observed"] is None
    assert sand["scale_error_dex"] == pytest.approx(0.3)
    assert sand["loop_outcomes"] == {"missed": 1, "right": 1}
    assert table["fluid / fluid"]["scale_error_dex"] is None
    assert table["all"]["recordings"] == 3
    assert table["all"]["cd_future"] == pytest.approx((0.006 + 0.010 + 0.005) / 3)


def test_the_suite_report_names_the_objects_the_views_do_not_show_whole(tmp_path):
    objects = [{"name": "ball", "family": "elastic"}, {"name": "box", "family": "plastic"}]
    run_report = {"estimates": {"objects": objects},
                  "metrics": {"observed": {"cd": 0.004}, "future": {"cd": 0.02}}, "frames": 61, "fitted_frames": 43,
                  "views": {"ball": {"cut": [30, 31, 32], "missing": [33, 34], "cameras": ["cam1"]}}}
    entry = summarise(Item("throw", tmp_path), run_report, None, None) | {"seconds": {"total": 300.0}}
    assert entry["views"] == {"ball": {"cut": 3, "missing": 2}}
    assert "views" not in summarise(Item("rest", tmp_path), {**run_report, "views": {}}, None, None)
    text = markdown({"recordings": 1, "done": 1, "failed": 0, "interrupted": False,
                     "per_pair": aggregate([entry]), "per_recording": [entry]}, None)
    assert "throw: ball cut by an image border in 3 frames, no geometry in 2" in text


def test_the_scale_error_is_the_mean_absolute_log10_ratio_of_the_scale_parameters_only():
    errors = {"ball": {"E": {"log10_ratio": -0.4}, "nu": {"abs": 0.05}, "friction": {"rel": 0.5}},
              "clay": {"yield_stress": {"log10_ratio": 0.2}}, "scene": {"ground.friction": {"rel": 0.1}}}
    assert scale_error(errors) == pytest.approx(0.3)
    assert scale_error({"ball": {"nu": {"abs": 0.05}}}) is None


def _loop_report(named: list[tuple[str, dict]]) -> dict:
    return {"verdict": "explained" if named else "nothing to explain",
            "accepted": [{"name": n, "values": v} for n, v in named],
            "before": {"centroid_error": {"held_out": 0.02}}, "after": {"centroid_error": {"held_out": 0.005}},
            "rounds": [{"control": None}, {"control": {"centroid_error": {"held_out": 0.018}}}],
            "reconstruction_floor": {"held_out": 0.001}}


def test_the_loop_is_judged_against_the_truths_undeclared_effects():
    truth = {"effects": [{"type": "drag", "declared": False, "params": {"coefficient": {"ball": 2.0}}},
                         {"type": "mask_noise", "declared": False, "params": {}},
                         {"type": "wind", "declared": True, "params": {"a": [0.5, 0, 0]}}]}
    right = judge(_loop_report([("drag", {"coefficient[ball]": 2.5})]), truth)
    assert right["expected"] == ["drag"] and right["outcome"] == "right"
    assert right["value_errors"]["drag"]["coefficient[ball]"] == pytest.approx(0.25)
    assert right["held_out_before"] == 0.02 and right["held_out_after"] == 0.005
    assert right["held_out_control"] == 0.018 and right["held_out_floor"] == 0.001
    assert judge(_loop_report([]), truth)["outcome"] == "missed"
    assert judge(_loop_report([("drag", {}), ("wind", {})]), truth)["outcome"] == "wrong name"
    assert "outcome" not in judge(_loop_report([]), None)


@pytest.fixture(scope="module")
def tiny_suite(tmp_path_factory):
    """Two recordings of the tiny suite and a corrupt copy of one (its MCAP file cut short)."""
    from mosiv_ros.synth.recorder import record
    from mosiv_ros.synth.scene_file import read_scene_file
    from mosiv_ros.synth.suite import suite_scenes

    root = tmp_path_factory.mktemp("batch")
    bags = root / "bags"
    for entry, document in suite_scenes("tiny")[1:3]:  # the cheapest: a stack and a collision
        scene = root / f"{entry['name']}.yaml"
        scene.write_text(yaml.safe_dump(document, sort_keys=False))
        record(read_scene_file(scene), bags / entry["name"], seed=0)
    corrupt = shutil.copytree(bags / entry["name"], bags / "corrupt")
    mcap = next(corrupt.glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[:3000])
    return bags


@pytest.fixture
def tiny_params(tmp_path):
    """The fast test budget with a two-sample search: a recording's run and loop in seconds."""
    from synth_scenes import FAST_PARAMS

    params = copy.deepcopy(FAST_PARAMS)
    identify = params["identify_node"]["ros__parameters"]
    identify["search"].update(samples=2, frames=3)
    identify.update(device="cpu", cpu_workers=1)
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(params))
    return path


@pytest.mark.slow
def test_a_batch_on_a_local_ray_reports_the_corrupt_recording_finishes_the_rest_and_resumes(
        tiny_suite, tiny_params, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("RAY_DEFAULT_OBJECT_STORE_MAX_MEMORY_BYTES", str(100 * 2**20))
    monkeypatch.setenv("RAY_USAGE_STATS_ENABLED", "0")
    out = tmp_path / "out"
    command = ["batch", str(tiny_suite), "--out", str(out), "--close-loop", "--params-file", str(tiny_params),
               "--cpus", "2", "--no-render"]
    assert main(command) == 1  # a recording failed
    printed = capsys.readouterr()
    good = sorted(p.name for p in tiny_suite.iterdir() if p.name != "corrupt")
    assert "corrupt failed: BagError" in printed.err
    assert "1 running" in printed.out  # two workers: while one recording fails, another runs
    assert "2/3 done (0 from before), 0 running, 1 failed, 0 waiting" in printed.out.splitlines()[-2]
    assert "BagError" in (out / "corrupt" / "error.txt").read_text()
    assert not (out / "corrupt" / SUMMARY).exists()
    report = json.loads((out / "batch.json").read_text())
    assert (report["recordings"], report["done"], report["failed"], report["interrupted"]) == (3, 2, 1, False)
    for name in good:
        summary = json.loads((out / name / SUMMARY).read_text())
        assert summary["status"] == "done" and summary["pair"] == " / ".join(name.split("__")[i].split("_")[0]
                                                                             for i in (0, 1))
        for part in ("observed", "future"):
            assert 0 < summary["scores"][part]["cd"] < 0.2 and 0 < summary["scores"][part]["emd"] < 0.5
            assert 0 < summary["scores"][part]["cd_truth"] < 0.2
        assert summary["parameter_errors"] and summary["scale_error_dex"] >= 0
        assert summary["loop"]["outcome"] in ("right", "missed", "wrong name")
        assert summary["seconds"]["total"] >= summary["seconds"]["run"] + summary["seconds"]["close_loop"] > 0
        assert (out / name / "run" / "report.json").is_file()
        assert (out / name / "close_loop" / "close_loop.json").is_file()
        assert report["per_pair"][summary["pair"]]["cd_observed"] == pytest.approx(summary["scores"]["observed"]["cd"])
    assert report["per_pair"]["all"]["recordings"] == 2
    markdown = (out / "batch.md").read_text()
    assert "| corrupt | | failed: BagError" in markdown and "![batch.png](batch.png)" in markdown
    assert (out / "batch.png").stat().st_size > 0

    finished = {name: (out / name / SUMMARY).stat().st_mtime_ns for name in good}
    (out / "corrupt" / "error.txt").unlink()
    assert main(command) == 1  # resumed: the finished ones skipped, the corrupt one tried again
    printed = capsys.readouterr()
    assert "2/3 done (2 from before), 1 running, 0 failed, 0 waiting" in printed.out
    assert {name: (out / name / SUMMARY).stat().st_mtime_ns for name in good} == finished
    assert "BagError" in (out / "corrupt" / "error.txt").read_text()
    again = json.loads((out / "batch.json").read_text())
    assert [e for e in again["per_recording"] if e["status"] == "done"] == [
        e for e in report["per_recording"] if e["status"] == "done"]


@pytest.mark.slow
def test_a_recordings_fit_checkpoints_in_its_folder_and_a_rerun_resumes_it_to_the_same_scores(
        tiny_suite, tiny_params, tmp_path):
    # a task stopped mid-fit (Ctrl-C, a killed worker, a deadline) goes on from its checkpoint;
    # here the rerun resumes a finished fit, which ends where it ended
    from mosiv_ros.cli import run_config
    from mosiv_ros.config import HOLDOUT

    config = run_config(tiny_params, "cpu", {}, holdout=HOLDOUT, render=False)
    name = sorted(p.name for p in tiny_suite.iterdir() if p.name != "corrupt")[0]
    item, folder = Item(name, tiny_suite / name), tmp_path / name
    first = process(item, folder, config, None, "cpu")
    assert first["status"] == "done" and any((folder / "run" / "checkpoints").iterdir())
    assert "resuming identification" not in (folder / LOG_FILE).read_text()
    again = process(item, folder, config, None, "cpu")
    assert "resuming identification from " + str(folder / "run" / "checkpoints") in (folder / LOG_FILE).read_text()
    assert again["scores"] == first["scores"]


@pytest.mark.slow
def test_ctrl_c_cancels_the_running_recording_and_keeps_the_finished_ones(tiny_suite, tiny_params, tmp_path):
    import os
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "out"
    env = {**os.environ, "RAY_DEFAULT_OBJECT_STORE_MAX_MEMORY_BYTES": str(100 * 2**20),
           "RAY_USAGE_STATS_ENABLED": "0"}
    batch = subprocess.Popen(  # one core: the recordings run one after another
        [sys.executable, "-m", "mosiv_ros", "batch", str(tiny_suite), "--out", str(out), "--params-file",
         str(tiny_params), "--cpus", "1", "--no-render"], env=env, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 400
    while not list(out.glob(f"*/{SUMMARY}")) and batch.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    batch.send_signal(signal.SIGINT)  # the next recording has just started
    printed, _ = batch.communicate(timeout=120)
    assert batch.returncode == 130, printed
    finished = [p.parent.name for p in out.glob(f"*/{SUMMARY}")]
    assert len(finished) == 1 and json.loads((out / finished[0] / SUMMARY).read_text())["status"] == "done"
    report = json.loads((out / "batch.json").read_text())
    assert report["interrupted"] and (report["done"], report["failed"]) == (1, 1)
    assert [e["recording"] for e in report["per_recording"] if e["status"] == "done"] == finished
    assert "interrupted" in printed and "interrupted (Ctrl-C)" in (out / "batch.md").read_text()
