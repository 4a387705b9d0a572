"""Node processes given faulty input: non-finite clouds, an empty particle cloud, a corrupt
checkpoint, a lost frame set, a failing worker, a malformed surface tracks cloud."""

from __future__ import annotations

import re

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import PointCloud2
from test_nodes_process import LATCHED, Listener

from mosiv_ros.config import LiftingConfig
from mosiv_ros.graph import Graph, NodeSpec
from mosiv_ros.identify.checkpoint import CHECKPOINT_FILE
from mosiv_ros.identify.estimates import ERROR, Estimates
from mosiv_ros.io.messages import pointcloud_from_msg, pointcloud_to_msg, rclpy_types
from mosiv_ros.io.recording import PointCloud
from mosiv_ros.nodes.common import STREAM_QOS
from mosiv_ros.nodes.outputs import statuses_of
from mosiv_ros.nodes.reconstruction_node import TRACKS_TOPIC
from mosiv_ros.prepare import RunConfig, prepare


@pytest.fixture(scope="module")
def prepared(drop_bag):
    """drop_bag's observed frames and particles, lifted as synth_scenes.FAST_PARAMS lifts them."""
    return prepare(drop_bag, RunConfig(lifting=LiftingConfig(particle_spacing=0.015)))


def _msg(cloud: PointCloud):
    return pointcloud_to_msg(rclpy_types(), cloud.xyz, cloud.object_id, cloud.stamp_ns, "world", cloud.fields)


def _nan_copy(cloud: PointCloud):
    """The same frame (same stamp) with every coordinate NaN."""
    return _msg(PointCloud(np.full_like(cloud.xyz, np.nan), cloud.object_id, cloud.fields, cloud.stamp_ns))


def _estimates(listener: Listener) -> Estimates:
    return Estimates.from_statuses(statuses_of(listener.received["/mosiv/material_estimates"][-1]))


@pytest.mark.slow
def test_non_finite_clouds_are_dropped_and_never_replace_good_frames(drop_bag, prepared, fast_params, tmp_path):
    frames = [f.to_cloud() for f in prepared.frames[:6]]
    listener = Listener("nan_prober")
    try:
        observed = listener.node.create_publisher(PointCloud2, "/mosiv/observed_objects", STREAM_QOS)
        listener.subscribe(PointCloud2, "/mosiv/particles", LATCHED)
        listener.subscribe(DiagnosticArray, "/mosiv/material_estimates", LATCHED)
        specs = [NodeSpec("lifting_node", {"scene": str(drop_bag)}),
                 NodeSpec("identify_node", {"scene": str(drop_bag), "window": 6, "output_yaml": ""})]
        with Graph(specs, params_file=fast_params, sink=None) as graph:
            assert listener.wait_for(lambda: observed.get_subscription_count() >= 2, 20)
            # a NaN copy first (it was lifted into 0 particles, and every later frame was ignored),
            # and a NaN copy of frame 2 with its stamp (it replaced the real frame in the fit)
            for msg in [_nan_copy(frames[0]), *map(_msg, frames[:3]), _nan_copy(frames[2]),
                        *map(_msg, frames[3:])]:
                observed.publish(msg)
            graph.nodes["identify_node"].wait_for_line("identification done", 300)
            assert listener.wait_for(lambda: listener.received["/mosiv/material_estimates"], 10)
            lifting, identify = graph.nodes["lifting_node"].lines, graph.nodes["identify_node"].lines
    finally:
        listener.close()
    dropped = "/mosiv/observed_objects: dropped malformed message: PointCloud2 field 'x':"
    assert sum(dropped in line for line in lifting) >= 1, "\n".join(lifting)
    assert sum(dropped in line for line in identify) == 2, "\n".join(identify)
    particles = pointcloud_from_msg(listener.received["/mosiv/particles"][-1])
    assert particles.stamp_ns == frames[0].stamp_ns and len(particles.xyz) == len(prepared.lifted.x)
    assert [o.level != ERROR for o in _estimates(listener).objects] == [True], _estimates(listener).objects


@pytest.mark.slow
def test_identify_node_waits_out_an_empty_cloud_a_corrupt_checkpoint_a_lost_frame_and_a_failing_write(
        drop_bag, prepared, fast_params, tmp_path):
    checkpoints = tmp_path / "checkpoints"
    checkpoints.mkdir()
    (checkpoints / CHECKPOINT_FILE).write_bytes(b"PK\x03\x04\x14\x00\x00\x00")  # cut short while written
    output = tmp_path / "outputs" / "estimates.yaml"
    output.parent.mkdir()  # writable when the node starts (it checks); a file by the time it writes
    particles = prepared.lifted.to_cloud()
    empty = PointCloud(particles.xyz[:0], particles.object_id[:0],
                       {k: v[:0] for k, v in particles.fields.items()}, particles.stamp_ns)
    listener = Listener("identify_prober")
    try:
        lifted = listener.node.create_publisher(PointCloud2, "/mosiv/particles", LATCHED)
        observed = listener.node.create_publisher(PointCloud2, "/mosiv/observed_objects", STREAM_QOS)
        listener.subscribe(DiagnosticArray, "/mosiv/material_estimates", LATCHED)
        listener.subscribe(DiagnosticArray, "/diagnostics", 10)
        params = {"scene": str(drop_bag), "window": 6, "checkpoint_dir": str(checkpoints),
                  "output_yaml": str(output)}
        with Graph([NodeSpec("identify_node", params)], params_file=fast_params, sink=None) as graph:
            node = graph.nodes["identify_node"]
            assert listener.wait_for(lambda: observed.get_subscription_count() >= 1, 20)
            output.parent.rmdir()
            output.parent.write_text("")  # the estimates' directory is gone: the write fails
            lifted.publish(_msg(empty))  # it ended ERROR: "zero-size array to reduction operation"
            node.wait_for_line("is empty: no particle to simulate", 30)
            lifted.publish(_msg(particles))
            for k in (0, 1, 2, 4, 5, 6):  # frame set 3 lost: "observed frames are not evenly spaced"
                observed.publish(_msg(prepared.frames[k].to_cloud()))
            # the worker thread died silently on the checkpoint and would on the write
            failed = node.wait_for_line("identification failed: unexpected", 300)
            assert listener.wait_for(lambda: listener.received["/mosiv/material_estimates"], 10)
            assert listener.wait_for(lambda: any(s.level == bytes([2]) for m in listener.received["/diagnostics"]
                                                 for s in m.status), 10)
            assert node.process.poll() is None
            lines = list(node.lines)
    finally:
        listener.close()
    text = "\n".join(lines)
    assert f"cannot read checkpoint {checkpoints / CHECKPOINT_FILE} (BadZipFile" in text, text
    assert "1 of the 7 frames from stamp" in text and "lost frames 3)" in text, text
    assert str(output.parent) in failed and "Traceback" in text
    estimates = _estimates(listener)
    assert estimates.frames == 7 and [o.level != ERROR for o in estimates.objects] == [True], estimates.objects
    status = next(s for m in listener.received["/diagnostics"] for s in m.status if s.level == bytes([2]))
    assert status.name == "mosiv/identify" and str(output.parent) in status.message


@pytest.mark.slow
def test_identify_node_waits_for_the_surface_tracks_fits_them_and_drops_a_malformed_tracks_cloud(
        drop_bag, prepared, fast_params):
    # the tracks come after the window's frame sets, and the last frame's track cloud is lost:
    # the node waits for the others (a fit started at once had 0 of 6 frames tracked) but not
    # for ever
    tracks = [f.tracks.to_cloud() for f in prepared.frames[:6]]
    assert all(len(cloud.xyz) for cloud in tracks)  # the jelly's texture gives tracks from the first frame
    lacking = PointCloud(tracks[0].xyz, tracks[0].object_id, {"track_id": tracks[0].fields["track_id"]},
                         tracks[0].stamp_ns)
    listener = Listener("tracks_prober")
    try:
        lifted = listener.node.create_publisher(PointCloud2, "/mosiv/particles", LATCHED)
        observed = listener.node.create_publisher(PointCloud2, "/mosiv/observed_objects", STREAM_QOS)
        surface = listener.node.create_publisher(PointCloud2, TRACKS_TOPIC, STREAM_QOS)
        listener.subscribe(DiagnosticArray, "/mosiv/material_estimates", LATCHED)
        params = {"scene": str(drop_bag), "window": 6, "output_yaml": ""}
        with Graph([NodeSpec("identify_node", params)], params_file=fast_params, sink=None) as graph:
            node = graph.nodes["identify_node"]
            assert listener.wait_for(lambda: surface.get_subscription_count() >= 1
                                     and observed.get_subscription_count() >= 1, 20)
            lifted.publish(_msg(prepared.lifted.to_cloud()))
            for frame in prepared.frames[:6]:
                observed.publish(_msg(frame.to_cloud()))
            surface.publish(_msg(lacking))  # no confidence field: logged and dropped
            for cloud in tracks[:5]:
                surface.publish(_msg(cloud))
            node.wait_for_line("identification done", 300)
            assert listener.wait_for(lambda: listener.received["/mosiv/material_estimates"], 10)
            assert node.process.poll() is None
            text = "\n".join(node.lines)
    finally:
        listener.close()
    assert f"{TRACKS_TOPIC}: dropped malformed message: surface track cloud of stamp" in text, text
    assert "lacks field(s) ['confidence']" in text, text
    assert "fitting 6 frames from stamp" in text and "(5 with surface tracks)" in text, text
    attached = re.search(r"surface tracks: (\d+) attached to the particles", text)
    assert attached and int(attached.group(1)) > 0, text
    assert [o.level != ERROR for o in _estimates(listener).objects] == [True], _estimates(listener).objects
