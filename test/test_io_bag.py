"""Bags in the DESIGN.md layout: exact round trips, raw replay access, every bad-input error.

Bad bags are made from a good one by copying it message by message through rosbags with one
precise defect (``rewrite``), so each test proves one rule of the reader.
Also here: cross-camera frame matching (``recording.match_frames`` / ``FrameMatcher``).
"""

from __future__ import annotations

import copy
import dataclasses
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from scipy.spatial.transform import Rotation
from test_io_scene import alias_bomb

from mosiv_ros.cli import main
from mosiv_ros.io.bag import (
    STORAGES,
    chunk_checksums,
    iter_raw_messages,
    list_topics,
    read_custom_data,
    read_recording,
    write_recording,
)
from mosiv_ros.io.errors import BagError
from mosiv_ros.io.messages import (
    image_from_msg,
    image_to_msg,
    jazzy_typestore,
    rosbags_types,
    stamp_to_ns,
    transform_to_msg,
)
from mosiv_ros.io.recording import (
    Camera,
    Frame,
    FrameMatcher,
    Recording,
    match_frames,
)
from mosiv_ros.io.scene import SCENE_KEY, Scene, SceneObject, scene_to_yaml
from mosiv_ros.synth.shapes import make_shapes_recording

TYPES = rosbags_types()


def assert_recordings_equal(got: Recording, want: Recording) -> None:
    assert list(got.cameras) == list(want.cameras)
    for name, camera in want.cameras.items():
        other = got.cameras[name]
        assert other.name == name
        a, b = other.intrinsics, camera.intrinsics
        assert (a.width, a.height, a.distortion_model) == (b.width, b.height, b.distortion_model)
        np.testing.assert_array_equal(a.K, b.K)
        np.testing.assert_array_equal(a.D, b.D)
        np.testing.assert_allclose(other.T_world_optical, camera.T_world_optical, atol=1e-12)
        assert other.stamps_ns == camera.stamps_ns
        for f, g in zip(other.frames, camera.frames, strict=True):
            assert f.rgb.dtype == g.rgb.dtype and f.mask.dtype == g.mask.dtype
            np.testing.assert_array_equal(f.rgb, g.rgb)
            np.testing.assert_array_equal(f.mask, g.mask)
            assert (f.depth is None) == (g.depth is None)
            if g.depth is not None:
                assert f.depth.dtype == np.float32
                np.testing.assert_array_equal(f.depth, g.depth)  # NaN == NaN here
    assert got.scene == want.scene
    assert [s for s, _ in got.gripper_poses] == [s for s, _ in want.gripper_poses]
    for (_, T), (_, U) in zip(got.gripper_poses, want.gripper_poses, strict=True):
        np.testing.assert_allclose(T, U, atol=1e-12)


def rewrite(
    src: Path,
    dst: Path,
    edit: Callable[[str, object], object | None] | None = None,
    *,
    custom_data: dict[str, str] | None = None,
) -> Path:
    """Copy bag ``src`` to ``dst``, passing every (topic, message) through ``edit``.

    ``edit`` returns the message to write (changed or not) or None to drop it.
    """
    store = jazzy_typestore()
    with Reader(src) as reader, Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        for key, value in (read_custom_data(src) if custom_data is None else custom_data).items():
            writer.set_custom_data(key, value)
        connections = {}
        for connection, log_time, raw in reader.messages():
            msg = store.deserialize_cdr(raw, connection.msgtype)
            msg = edit(connection.topic, msg) if edit else msg
            if msg is None:
                continue
            if connection.topic not in connections:
                connections[connection.topic] = writer.add_connection(
                    connection.topic,
                    connection.msgtype,
                    typestore=store,
                    offered_qos_profiles=connection.ext.offered_qos_profiles,
                )
            writer.write(
                connections[connection.topic],
                log_time,
                store.serialize_cdr(msg, connection.msgtype),
            )
    return dst


def at(topic: str, stamp: int | None, change: Callable[[object], object | None]):
    """An ``edit`` applying ``change`` to the messages of ``topic`` (at ``stamp``, or all)."""

    def edit(t: str, msg: object) -> object | None:
        if t == topic and (stamp is None or stamp_to_ns(msg.header.stamp) == stamp):
            return change(msg)
        return msg

    return edit


def drop_topics(*topics: str):
    return lambda t, msg: None if t in topics else msg


@pytest.fixture(scope="module")
def stamps(small_recording) -> list[int]:
    return small_recording.cameras["cam0"].stamps_ns


# --- round trips --------------------------------------------------------------------------------


@pytest.mark.parametrize("storage", sorted(STORAGES))
def test_write_then_read_round_trips_every_array_and_stamp_exactly(
    small_recording, tmp_path, storage
):
    rng = np.random.default_rng(0)
    poses = []
    for stamp in small_recording.cameras["cam0"].stamps_ns:
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        T[:3, 3] = rng.uniform(-1, 1, 3)
        poses.append((stamp + 1, T))
    scene = Scene(
        objects=[
            *small_recording.scene.objects[:2],
            SceneObject(3, "blue_ball", "sand", {"E": 3e5}),
        ],
        gripper={"shape": "sphere", "radius": 0.02},
    )
    recording = dataclasses.replace(small_recording, scene=scene, gripper_poses=poses)
    path = write_recording(recording, tmp_path / "bag", storage=storage)
    assert (path / "metadata.yaml").is_file()
    back = read_recording(path)
    assert back.path == path
    assert_recordings_equal(back, recording)


def test_mono16_masks_with_large_ids_round_trip(small_recording, tmp_path):
    recording = copy.deepcopy(small_recording)
    for camera in recording.cameras.values():
        for frame in camera.frames:
            frame.mask = np.where(frame.mask == 3, 3000, frame.mask.astype(np.uint16))
    recording.scene.objects[2].id = 3000
    back = read_recording(write_recording(recording, tmp_path / "bag"))
    assert back.cameras["cam0"].frames[0].mask.dtype == np.uint16
    assert_recordings_equal(back, recording)


def test_recording_without_depth_round_trips(small_recording, tmp_path):
    recording = copy.deepcopy(small_recording)
    for camera in recording.cameras.values():
        for frame in camera.frames:
            frame.depth = None
    path = write_recording(recording, tmp_path / "bag", storage="sqlite3")
    assert "/cam0/depth/image_rect" not in list_topics(path)
    assert_recordings_equal(read_recording(path), recording)


def test_bgr_and_alpha_colour_and_millimetre_depth_read_as_rgb_and_metres(small_bag, small_recording, tmp_path):
    """Cameras' other common encodings (OpenCV's bgr8, alpha, REP 118's 16UC1 depth) read as the
    pipeline's RGB and metres: colour exactly, depth to the millimetre, 0 mm as no return."""
    colour = {"/cam0/color/image_raw": "bgr8", "/cam1/color/image_raw": "bgra8"}

    def reencode(topic, msg):
        if topic in colour or topic.endswith("/depth/image_rect"):
            stamp = stamp_to_ns(msg.header.stamp)
        if topic in colour:
            rgb = image_from_msg(msg)
            order = rgb[..., ::-1]
            pixels = np.dstack([order, np.full(rgb.shape[:2], 7, np.uint8)]) if colour[topic] == "bgra8" else order
            return image_to_msg(TYPES, np.ascontiguousarray(pixels), colour[topic], stamp, msg.header.frame_id)
        if topic.endswith("/depth/image_rect"):
            depth = image_from_msg(msg)
            millimetres = np.where(np.isfinite(depth), np.round(depth * 1000), 0).astype(np.uint16)
            millimetres[0, :3] = 0  # pixels without a return
            return image_to_msg(TYPES, millimetres, "16UC1", stamp, msg.header.frame_id)
        return msg

    back = read_recording(rewrite(small_bag, tmp_path / "bag", reencode))
    for name, camera in small_recording.cameras.items():
        for got, want in zip(back.cameras[name].frames, camera.frames, strict=True):
            np.testing.assert_array_equal(got.rgb, want.rgb)
            assert got.depth.dtype == np.float32
            assert np.isnan(got.depth[0, :3]).all()
            returned = np.isfinite(want.depth)
            returned[0, :3] = False
            assert np.array_equal(np.isfinite(got.depth), returned)
            assert np.abs(got.depth[returned] - want.depth[returned]).max() <= 0.0005 + 1e-6


def test_compressed_mcap_round_trips(small_recording, tmp_path):
    path = write_recording(small_recording, tmp_path / "bag", compress=True)
    assert_recordings_equal(read_recording(path), small_recording)


def test_writing_over_an_existing_path_raises_bag_error(small_recording, tmp_path):
    with pytest.raises(BagError, match="exists already"):
        write_recording(small_recording, tmp_path)


def test_camera_info_has_the_same_stamps_as_the_images(small_bag, stamps):
    store = jazzy_typestore()
    by_topic: dict[str, list[int]] = {}
    for raw in iter_raw_messages(small_bag, ["/cam0/color/image_raw", "/cam0/color/camera_info"]):
        msg = store.deserialize_cdr(raw.data, raw.msgtype)
        by_topic.setdefault(raw.topic, []).append(stamp_to_ns(msg.header.stamp))
        assert raw.log_time_ns == stamp_to_ns(msg.header.stamp)
    assert by_topic["/cam0/color/camera_info"] == by_topic["/cam0/color/image_raw"] == stamps


def test_scene_travels_in_custom_data(small_bag, small_recording):
    assert read_custom_data(small_bag) == {SCENE_KEY: scene_to_yaml(small_recording.scene)}


# --- raw access for the replay node -------------------------------------------------------------


def test_list_topics_gives_types_counts_and_offered_qos(small_bag):
    topics = list_topics(small_bag)
    assert topics["/tf_static"].msgtype == "tf2_msgs/msg/TFMessage"
    assert topics["/tf_static"].latched and not topics["/tf_static"].best_effort
    image = topics["/cam1/color/image_raw"]
    assert (image.msgtype, image.message_count) == ("sensor_msgs/msg/Image", 4)
    assert image.best_effort and not image.latched
    assert set(topics) == {"/tf_static"} | {
        f"/cam{i}/{suffix}"
        for i in (0, 1)
        for suffix in ("color/image_raw", "color/camera_info", "instance_mask", "depth/image_rect")
    }


def test_raw_messages_are_stored_cdr_in_log_time_order(small_bag, small_recording):
    raws = list(iter_raw_messages(small_bag))
    assert len(raws) == sum(t.message_count for t in list_topics(small_bag).values())
    assert raws[0].topic == "/tf_static"
    assert all(isinstance(r.data, bytes) for r in raws)
    times = [r.log_time_ns for r in raws]
    assert times == sorted(times)
    first_image = next(r for r in raws if r.topic == "/cam1/instance_mask")
    msg = jazzy_typestore().deserialize_cdr(first_image.data, first_image.msgtype)
    np.testing.assert_array_equal(
        np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.width),
        small_recording.cameras["cam1"].frames[0].mask,
    )


def test_raw_messages_deserialize_with_rclpy(small_bag, small_recording):
    serialization = pytest.importorskip("rclpy.serialization")
    from sensor_msgs.msg import Image

    from mosiv_ros.io.messages import image_from_msg

    raw = next(iter_raw_messages(small_bag, ["/cam0/color/image_raw"]))
    msg = serialization.deserialize_message(raw.data, Image)
    np.testing.assert_array_equal(
        image_from_msg(msg), small_recording.cameras["cam0"].frames[0].rgb
    )


# --- not a bag ----------------------------------------------------------------------------------

READERS = [read_recording, list_topics, lambda p: list(iter_raw_messages(p)), read_custom_data]


@pytest.mark.parametrize("read", READERS)
def test_missing_path_raises_bag_error_naming_it(tmp_path, read):
    with pytest.raises(BagError) as info:
        read(tmp_path / "nothing")
    assert str(info.value) == f"{tmp_path / 'nothing'}: does not exist"
    assert info.value.topic is None


@pytest.mark.parametrize("read", READERS)
def test_plain_file_raises_bag_error(tmp_path, read):
    (tmp_path / "x.mcap").write_bytes(b"\x89MCAP0\r\n")
    with pytest.raises(BagError, match="is a file, not a rosbag2 directory"):
        read(tmp_path / "x.mcap")


@pytest.mark.parametrize("read", READERS)
def test_directory_without_metadata_raises_bag_error(tmp_path, read):
    with pytest.raises(BagError, match="no metadata.yaml"):
        read(tmp_path)


def test_unreadable_metadata_raises_bag_error(small_bag, tmp_path):
    bag = Path(shutil.copytree(small_bag, tmp_path / "bag"))
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")
    with pytest.raises(BagError, match=f"^{bag}: "):
        read_recording(bag)


def test_metadata_that_is_not_utf8_raises_bag_error_naming_the_file(small_bag, tmp_path, capsys):
    bag = Path(shutil.copytree(small_bag, tmp_path / "bag"))
    metadata = bag / "metadata.yaml"
    metadata.write_bytes(metadata.read_bytes().replace(b"objects:", b"obj\xfects:", 1))
    with pytest.raises(BagError, match=r"metadata.yaml: not UTF-8 text \(byte 0xfe at offset \d+\)"):
        read_recording(bag)
    assert main(["info", str(bag)]) == 2
    assert f"{bag}: metadata.yaml: not UTF-8 text" in capsys.readouterr().err


def test_a_params_file_that_is_not_utf8_is_refused_naming_it(small_bag, tmp_path, capsys):
    params = tmp_path / "params.yaml"
    params.write_bytes(b"identify_node:\n  ros__parameters: {device: \xfecpu}\n")
    assert main(["run", str(small_bag), "--out", str(tmp_path / "out"), "--params-file", str(params)]) == 2
    assert f"mosiv run: error: {params}: not UTF-8 text (byte 0xfe at offset 43)" in capsys.readouterr().err


# --- damaged storage ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sqlite_bag(small_recording, tmp_path_factory):
    return write_recording(
        small_recording, tmp_path_factory.mktemp("sq") / "bag", storage="sqlite3"
    )


def damaged_copy(bag: Path, tmp_path: Path, damage: Callable[[Path], None]) -> Path:
    copy_path = Path(shutil.copytree(bag, tmp_path / "damaged"))
    (storage,) = [p for p in copy_path.iterdir() if p.suffix in (".mcap", ".db3")]
    damage(storage)
    return copy_path


def truncate(fraction: float) -> Callable[[Path], None]:
    def damage(path: Path) -> None:
        size = path.stat().st_size
        with path.open("r+b") as file:
            file.truncate(int(size * fraction))

    return damage


@pytest.mark.parametrize("fraction", [0.1, 0.5, 0.9, 0.995])
def test_truncated_mcap_raises_bag_error_naming_the_bag(small_bag, tmp_path, fraction):
    bag = damaged_copy(small_bag, tmp_path, truncate(fraction))
    with pytest.raises(BagError) as info:
        read_recording(bag)
    assert str(info.value).startswith(f"{bag}")
    with pytest.raises(BagError):
        list(iter_raw_messages(bag))


@pytest.mark.parametrize("fraction", [0.1, 0.5, 0.9])
def test_truncated_sqlite_raises_bag_error_naming_the_bag(sqlite_bag, tmp_path, fraction):
    bag = damaged_copy(sqlite_bag, tmp_path, truncate(fraction))
    with pytest.raises(BagError) as info:
        read_recording(bag)
    assert str(info.value).startswith(f"{bag}")


def overwrite_middle(path: Path) -> None:
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 4096] = bytes(range(256)) * 16
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("bag_fixture", ["small_bag", "sqlite_bag"])
def test_corrupt_storage_bytes_raise_bag_error(request, tmp_path, bag_fixture):
    bag = damaged_copy(request.getfixturevalue(bag_fixture), tmp_path, overwrite_middle)
    with pytest.raises(BagError, match=f"^{bag}"):
        read_recording(bag)


def flip_a_bit_inside_the_largest_chunk(path: Path) -> None:
    """Flip one bit in the middle of the records of the MCAP file's largest chunk (image data)."""
    data = bytearray(path.read_bytes())
    chunks, offset = [], 8  # after the magic: records of opcode (1 byte), length (8), content
    while data[offset] != 0x0F:  # up to the end of the data section
        length = int.from_bytes(data[offset + 1 : offset + 9], "little")
        if data[offset] == 0x06:
            chunks.append((length, offset + 9))
        offset += 9 + length
    length, content = max(chunks)
    data[content + length // 2] ^= 0x10
    path.write_bytes(bytes(data))


def test_a_bit_flipped_inside_a_chunk_of_a_new_bag_is_a_checksum_error(small_bag, tmp_path):
    assert chunk_checksums(small_bag) == (1, 1)  # the one chunk carries its CRC
    bag = damaged_copy(small_bag, tmp_path, flip_a_bit_inside_the_largest_chunk)
    with pytest.raises(BagError, match="checksum mismatch"):
        read_recording(bag)
    with pytest.raises(BagError, match="checksum mismatch"):
        list(iter_raw_messages(bag))


def test_a_compressed_bag_carries_checksums_and_a_bag_without_them_still_reads(small_recording, small_bag,
                                                                               tmp_path, capsys):
    large = make_shapes_recording(n_frames=4, n_cameras=2, width=320, height=240)  # several chunks
    compressed = write_recording(large, tmp_path / "zstd", compress=True)
    with_crc, chunks = chunk_checksums(compressed)
    assert with_crc == chunks > 1
    assert_recordings_equal(read_recording(compressed), large)
    older = rewrite(small_bag, tmp_path / "older")  # rosbags' own writer: CRC 0, "none"
    assert chunk_checksums(older) == (0, 1)
    assert_recordings_equal(read_recording(older), small_recording)
    assert main(["info", str(older)]) == 0
    assert "storage: mcap, 1 chunk, none with a checksum" in capsys.readouterr().out
    assert main(["info", str(compressed)]) == 0
    assert f"storage: mcap, {chunks} chunks, all with a checksum (CRC32)" in capsys.readouterr().out
    sqlite = write_recording(small_recording, tmp_path / "sqlite", storage="sqlite3")
    assert chunk_checksums(sqlite) is None
    assert main(["info", str(sqlite)]) == 0
    assert "storage: sqlite3 (no chunk checksums)" in capsys.readouterr().out


def test_storage_holding_fewer_messages_than_metadata_says_is_an_error(small_bag, tmp_path):
    bag = rewrite(small_bag, tmp_path / "bag", at("/cam1/instance_mask", None, lambda m: m))
    metadata = (bag / "metadata.yaml").read_text()
    (bag / "metadata.yaml").write_text(metadata.replace("message_count: 4\n", "message_count: 5\n"))
    with pytest.raises(BagError, match="declares 5 messages, the storage holds 4") as info:
        read_recording(bag)
    assert info.value.topic is not None


# --- bad content --------------------------------------------------------------------------------


def test_bag_without_camera_topics_raises_bag_error(small_bag, tmp_path):
    bag = rewrite(small_bag, tmp_path / "bag", lambda t, m: m if t == "/tf_static" else None)
    with pytest.raises(BagError, match=r"no camera topics .* topics in bag: \['/tf_static'\]"):
        read_recording(bag)


def test_missing_camera_info_raises_bag_error_naming_topic_and_camera(small_bag, tmp_path):
    bag = rewrite(small_bag, tmp_path / "bag", drop_topics("/cam1/color/camera_info"))
    with pytest.raises(BagError) as info:
        read_recording(bag)
    assert info.value.topic == "/cam1/color/camera_info"
    assert str(info.value) == (
        f"{bag}: topic /cam1/color/camera_info: no CameraInfo for camera 'cam1'"
    )


def test_missing_tf_static_raises_bag_error(small_bag, tmp_path):
    bag = rewrite(small_bag, tmp_path / "bag", drop_topics("/tf_static"))
    with pytest.raises(BagError, match="topic /tf_static: topic missing"):
        read_recording(bag)


@pytest.mark.parametrize(("topic", "encoding", "expected"), [
    ("/cam0/instance_mask", "rgb8", "('mono8', 'mono16')"),
    ("/cam0/color/image_raw", "32FC1", "('rgb8', 'bgr8', 'rgba8', 'bgra8')"),
])
def test_an_image_in_another_kinds_encoding_raises_bag_error_naming_the_encodings(
    small_bag, tmp_path, stamps, topic, encoding, expected
):
    def reencode(msg):
        shape = (msg.height, msg.width, 3) if encoding == "rgb8" else (msg.height, msg.width)
        pixels = np.zeros(shape, np.uint8 if encoding == "rgb8" else np.float32)
        return image_to_msg(TYPES, pixels, encoding, stamp_to_ns(msg.header.stamp), "cam0_optical")

    bag = rewrite(small_bag, tmp_path / "bag", at(topic, stamps[2], reencode))
    with pytest.raises(BagError) as info:
        read_recording(bag)
    assert info.value.topic == topic
    assert f"encoding '{encoding}' at stamp {stamps[2]}, expected {expected}" in str(info.value)


def test_depth_of_another_size_than_the_image_raises_bag_error(small_bag, tmp_path, stamps):
    def shrink(msg):
        depth = np.ones((msg.height // 2, msg.width // 2), np.float32)
        return image_to_msg(TYPES, depth, "32FC1", stamp_to_ns(msg.header.stamp), "cam0_optical")

    bag = rewrite(small_bag, tmp_path / "bag", at("/cam0/depth/image_rect", stamps[1], shrink))
    with pytest.raises(BagError) as info:
        read_recording(bag)
    assert info.value.topic == "/cam0/depth/image_rect"
    assert f"stamp {stamps[1]}" in str(info.value) and "depth" in info.value.problem


def test_image_data_shorter_than_step_times_height_raises_bag_error(small_bag, tmp_path, stamps):
    def cut(msg):
        msg.data = msg.data[:-1]
        return msg

    bag = rewrite(small_bag, tmp_path / "bag", at("/cam1/color/image_raw", stamps[3], cut))
    with pytest.raises(BagError) as info:
        read_recording(bag)
    assert info.value.topic == "/cam1/color/image_raw"
    assert f"message at stamp {stamps[3]}: Image.data" in info.value.problem
    assert "step * height" in info.value.problem


def test_camera_info_of_another_size_raises_bag_error(small_bag, tmp_path):
    def widen(msg):
        msg.width += 2
        return msg

    bag = rewrite(small_bag, tmp_path / "bag", at("/cam0/color/camera_info", None, widen))
    with pytest.raises(BagError, match="size 26x18 differs from the images' 24x18") as info:
        read_recording(bag)
    assert info.value.topic == "/cam0/color/camera_info"


def test_calibration_changing_over_time_raises_bag_error(small_bag, tmp_path, stamps):
    def refocus(msg):
        msg.k = msg.k * 1.01
        return msg

    bag = rewrite(small_bag, tmp_path / "bag", at("/cam0/color/camera_info", stamps[2], refocus))
    with pytest.raises(BagError, match=f"calibration changes at stamp {stamps[2]}"):
        read_recording(bag)


def _calibration(field: str, value: float):
    """A change of one CameraInfo calibration value: ``k[i]`` or ``d[i]``."""
    name, index = field[0], int(field[2:-1])

    def change(msg):
        values = getattr(msg, name).copy()
        values[index] = value
        setattr(msg, name, values)
        return msg

    return change


BAD_CALIBRATIONS = [  # (CameraInfo field, value, where it shows, what the error says)
    ("k[0]", 0.0, "fx", "must be a positive, finite number of pixels, got 0.0"),
    ("k[0]", float("nan"), "fx", "must be a positive, finite number of pixels, got nan"),
    ("k[4]", -300.0, "fy", "must be a positive, finite number of pixels, got -300.0"),
    ("k[2]", 40.0, "cx", "principal point"),
    ("k[5]", float("inf"), "cy", "principal point"),
    ("d[1]", float("nan"), "distortion", "must be finite"),
]


@pytest.mark.parametrize(("field", "value", "name", "problem"), BAD_CALIBRATIONS,
                         ids=[f"{f}={v}" for f, v, _, _ in BAD_CALIBRATIONS])
@pytest.mark.parametrize("every_stamp", [True, False], ids=["every stamp", "one stamp"])
def test_bad_calibration_raises_bag_error_naming_camera_and_field(small_bag, tmp_path, stamps, capsys, field,
                                                                    value, name, problem, every_stamp):
    stamp = None if every_stamp else stamps[2]
    bag = rewrite(small_bag, tmp_path / "bag", at("/cam1/color/camera_info", stamp, _calibration(field, value)))
    with pytest.raises(BagError) as info:
        read_recording(bag)
    assert info.value.topic == "/cam1/color/camera_info"  # the camera
    assert f"CameraInfo: {field} ({name})" in info.value.problem and problem in info.value.problem
    assert "calibration changes" not in info.value.problem
    assert main(["info", str(bag)]) == 2
    assert f"topic /cam1/color/camera_info: message at stamp {stamp or stamps[0]}: CameraInfo: {field} ({name})" \
        in capsys.readouterr().err


def test_image_without_mask_of_the_same_stamp_raises_bag_error(small_bag, tmp_path, stamps):
    bag = rewrite(small_bag, tmp_path / "bag", at("/cam0/instance_mask", stamps[1], lambda m: None))
    with pytest.raises(BagError) as info:
        read_recording(bag)
    assert info.value.topic == "/cam0/instance_mask"
    assert "of /cam0/color/image_raw have no mask" in info.value.problem
    assert "exact header stamp" in info.value.problem and str(stamps[1]) in info.value.problem


def test_mask_stamp_off_by_one_nanosecond_does_not_pair(small_bag, tmp_path, stamps):
    def shift(msg):
        msg.header.stamp.nanosec += 1
        return msg

    bag = rewrite(small_bag, tmp_path / "bag", at("/cam1/instance_mask", stamps[0], shift))
    with pytest.raises(BagError, match=f"{stamps[0]}") as info:
        read_recording(bag)
    assert info.value.topic == "/cam1/instance_mask"


def test_missing_depth_frame_raises_bag_error(small_bag, tmp_path, stamps):
    bag = rewrite(
        small_bag, tmp_path / "bag", at("/cam1/depth/image_rect", stamps[3], lambda m: None)
    )
    with pytest.raises(BagError, match=f"have no depth .*{stamps[3]}") as info:
        read_recording(bag)
    assert info.value.topic == "/cam1/depth/image_rect"


def test_mask_ids_not_in_the_scene_raise_bag_error_naming_ids_camera_and_stamp(
    small_bag, tmp_path, stamps
):
    def paint(msg):
        mask = np.zeros((msg.height, msg.width), np.uint8)
        mask[0, :2], mask[1, 0] = 9, 7
        return image_to_msg(TYPES, mask, "mono8", stamp_to_ns(msg.header.stamp), "cam1_optical")

    bag = rewrite(small_bag, tmp_path / "bag", at("/cam1/instance_mask", stamps[2], paint))
    with pytest.raises(BagError) as info:
        read_recording(bag)
    assert info.value.topic == "/cam1/instance_mask"
    assert info.value.problem == (
        f"camera 'cam1' stamp {stamps[2]}: mask ids [7, 9] are not declared in the scene "
        "(declared ids: [1, 2, 3])"
    )
    assert read_recording(bag, check_ids=False).cameras["cam1"].frames[2].mask.max() == 9
    undeclared = rewrite(bag, tmp_path / "no_scene", custom_data={})
    assert read_recording(undeclared).scene == Scene()


def test_invalid_scene_in_custom_data_raises_bag_error(small_bag, tmp_path):
    bad = "objects: [{id: 1, name: a, family: jelly}]"
    bag = rewrite(small_bag, tmp_path / "bag", custom_data={SCENE_KEY: bad})
    with pytest.raises(BagError, match=r"scene declaration .*objects\[0\].family"):
        read_recording(bag)


def test_an_alias_bomb_in_the_scene_declaration_gives_mosiv_info_one_short_line(small_bag, tmp_path, capsys):
    bag = rewrite(small_bag, tmp_path / "bag", custom_data={SCENE_KEY: alias_bomb(6, "objects: [BOMB]")})
    assert main(["info", str(bag)]) == 2
    err = capsys.readouterr().err
    assert "scene declaration (custom_data 'mosiv.scene'): <string>: invalid YAML: its aliases expand it" in err
    assert len(err) < 1000


def test_mosiv_info_shows_cameras_objects_declared_parameters_ground_and_effects(
        small_bag, small_recording, capsys, tmp_path):
    names = [o.name for o in small_recording.scene.objects]
    declared = (f"objects: [{{id: 1, name: {names[0]}, family: elastic, params: {{density: 1200}}}}, "
                f"{{id: 2, name: {names[1]}}}, {{id: 3, name: {names[2]}, family: sand}}]\n"
                "ground: {height: 0.01, friction: 0.4}\n"
                f"effects: [{{name: drag, params: {{coefficient: {{{names[0]}: 1.5}}}}}}]\n")
    bag = rewrite(small_bag, tmp_path / "bag", custom_data={SCENE_KEY: declared})
    assert main(["info", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "camera cam0: 24x18" in out and "4 frames, with depth" in out
    assert f"object 1: {names[0]} (elastic); declared parameters: density=1200" in out
    assert f"object 2: {names[1]} (family not declared); declared parameters: none" in out
    assert "ground: height 0.01 m, normal (0.0, 0.0, 1.0), friction 0.4" in out
    assert f"declared effect drag: {{'coefficient': {{'{names[0]}': 1.5}}}}" in out
    assert main(["info", str(small_bag)]) == 0  # the analytic sample declares its floor alone
    assert "ground: height 0 m, normal (0.0, 0.0, 1.0), friction fitted (not declared)" in capsys.readouterr().out
    only_objects = "objects: [" + ", ".join(f"{{id: {i}, name: {n}}}" for i, n in enumerate(names, 1)) + "]\n"
    floorless = rewrite(small_bag, tmp_path / "floorless", custom_data={SCENE_KEY: only_objects})
    assert main(["info", str(floorless)]) == 0
    assert "ground: not declared (no floor in the simulation)" in capsys.readouterr().out


def test_extrinsics_follow_a_chain_of_static_transforms_in_either_direction(
    small_bag, small_recording, tmp_path
):
    T_world_rig = np.eye(4)
    T_world_rig[:3, 3] = [0.3, -0.2, 1.0]
    T_world_rig[:3, :3] = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    T_rig_link = np.eye(4)
    T_rig_link[:3, 3] = [0.0, 0.1, 0.0]
    expected = {n: c.T_world_optical for n, c in small_recording.cameras.items()}
    T_link_optical = np.linalg.inv(T_world_rig @ T_rig_link) @ expected["cam0"]

    def chain(msg):
        # A tree rooted at 'rig': world is rig's child, so world -> cam0_optical goes up, then down.
        stamp = stamp_to_ns(msg.transforms[0].header.stamp)
        msg.transforms = [
            transform_to_msg(TYPES, "rig", "world", np.linalg.inv(T_world_rig), stamp),
            transform_to_msg(TYPES, "rig", "cam0_link", T_rig_link, stamp),
            transform_to_msg(TYPES, "cam0_link", "cam0_optical", T_link_optical, stamp),
            transform_to_msg(TYPES, "world", "cam1_optical", expected["cam1"], stamp),
        ]
        return msg

    bag = rewrite(small_bag, tmp_path / "bag", at("/tf_static", None, chain))
    recording = read_recording(bag)
    for name, T in expected.items():
        np.testing.assert_allclose(recording.cameras[name].T_world_optical, T, atol=1e-12)


def test_camera_frame_unreachable_from_world_raises_bag_error(small_bag, tmp_path):
    def orphan(msg):
        msg.transforms[1].header.frame_id = "elsewhere"
        return msg

    bag = rewrite(small_bag, tmp_path / "bag", at("/tf_static", None, orphan))
    with pytest.raises(
        BagError, match="no chain of static transforms from 'world' to 'cam1_optical'"
    ):
        read_recording(bag)


# --- frame matching (recording.py) --------------------------------------------------------------


def frame(stamp: int) -> Frame:
    return Frame(stamp, np.zeros((2, 2, 3), np.uint8), np.zeros((2, 2), np.uint8))


def cameras_with(stamps_by_camera: dict[str, list[int]]) -> dict[str, Camera]:
    return {
        name: Camera(name, _tiny_intrinsics(), np.eye(4), [frame(s) for s in stamps])
        for name, stamps in stamps_by_camera.items()
    }


def _tiny_intrinsics():
    from mosiv_ros.io.recording import CameraIntrinsics

    return CameraIntrinsics(2, 2, np.eye(3))


MS = 1_000_000


def test_frames_with_jitter_within_tolerance_form_complete_sets():
    rng = np.random.default_rng(1)
    base = [1_000 * MS + k * 100 * MS for k in range(10)]
    stamps = {c: [b + int(rng.integers(-2 * MS, 2 * MS)) for b in base] for c in ("a", "b", "c")}
    sets = match_frames(cameras_with(stamps), tolerance_ns=5 * MS)
    assert len(sets) == 10
    for k, frame_set in enumerate(sets):
        assert list(frame_set.frames) == ["a", "b", "c"]
        assert frame_set.stamp_ns == min(stamps[c][k] for c in stamps)
        assert all(f.stamp_ns == stamps[c][k] for c, f in frame_set.frames.items())


def test_a_camera_missing_a_frame_is_absent_from_that_set_only():
    base = [k * 100 * MS for k in range(5)]
    stamps = {"a": base, "b": base[:2] + base[3:], "c": [s + MS for s in base]}
    sets = match_frames(cameras_with(stamps), tolerance_ns=5 * MS)
    assert [sorted(s.frames) for s in sets] == [["a", "b", "c"]] * 2 + [["a", "c"]] + [
        ["a", "b", "c"]
    ] * 2
    assert [s.stamp_ns for s in sets] == base


def test_frames_further_apart_than_tolerance_are_not_matched():
    sets = match_frames(cameras_with({"a": [0], "b": [6 * MS]}), tolerance_ns=5 * MS)
    assert [(s.stamp_ns, list(s.frames)) for s in sets] == [(0, ["a"]), (6 * MS, ["b"])]


def test_matcher_completes_sets_as_frames_stream_in_out_of_order():
    matcher = FrameMatcher(["a", "b"], tolerance_ns=5 * MS)
    assert matcher.add("b", frame(101 * MS)) == []
    assert matcher.add("a", frame(200 * MS)) == []
    (first,) = matcher.add("a", frame(99 * MS))
    assert first.stamp_ns == 99 * MS and first.frames["b"].stamp_ns == 101 * MS
    (second,) = matcher.add("b", frame(203 * MS))
    assert second.stamp_ns == 200 * MS
    assert matcher.pending == 0 and matcher.dropped == 0


def test_frame_joins_the_set_closest_in_time():
    matcher = FrameMatcher(["a", "b"], tolerance_ns=10 * MS)
    matcher.add("a", frame(0))
    matcher.add("a", frame(8 * MS))
    (joined,) = matcher.add("b", frame(7 * MS))
    assert joined.frames["a"].stamp_ns == 8 * MS
    assert [s.stamp_ns for s in matcher.flush()] == [0]


def test_stale_partial_sets_are_dropped_and_counted():
    matcher = FrameMatcher(["a", "b"], tolerance_ns=5 * MS, horizon_ns=300 * MS)
    for k in range(5):  # camera b is silent
        matcher.add("a", frame(k * 100 * MS))
    assert matcher.dropped == 1 and matcher.pending == 4
    assert matcher.flush()[0].stamp_ns == 100 * MS


def test_matcher_rejects_an_unknown_camera():
    with pytest.raises(ValueError, match="unknown camera 'z'"):
        FrameMatcher(["a"]).add("z", frame(0))


def test_frames_of_a_bag_match_into_complete_sets(small_bag):
    recording = read_recording(small_bag)
    sets = match_frames(recording.cameras)
    assert [s.stamp_ns for s in sets] == recording.cameras["cam0"].stamps_ns
    assert all(list(s.frames) == ["cam0", "cam1"] for s in sets)
