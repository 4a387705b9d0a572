"""numpy <-> message conversions, with the rosbags and the rclpy message classes alike."""

from __future__ import annotations

import array
import importlib.util

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mosiv_ros.io.errors import MessageError
from mosiv_ros.io.messages import (
    camera_image_from_msg,
    camera_info_from_msg,
    camera_info_to_msg,
    image_from_msg,
    image_to_msg,
    jazzy_typestore,
    ns_to_stamp,
    pointcloud_from_msg,
    pointcloud_to_msg,
    pose_stamped_from_msg,
    pose_stamped_to_msg,
    rclpy_types,
    rosbags_types,
    stamp_to_ns,
    tf_message,
    transform_from_msg,
    transform_to_msg,
)
from mosiv_ros.io.recording import CameraIntrinsics

STAMP = 1_700_000_000_123_456_789
RNG = np.random.default_rng(7)
HAS_TF2_MSGS = importlib.util.find_spec("tf2_msgs") is not None


@pytest.fixture(params=["rosbags", "rclpy"])
def types(request):
    return rosbags_types() if request.param == "rosbags" else rclpy_types()


def sample_image(encoding: str, height: int = 5, width: int = 7) -> np.ndarray:
    if encoding in ("rgb8", "bgr8", "rgba8", "bgra8"):
        return RNG.integers(0, 256, (height, width, len(encoding) - 1), dtype=np.uint8)
    if encoding == "mono8":
        return RNG.integers(0, 256, (height, width), dtype=np.uint8)
    if encoding in ("mono16", "16UC1"):
        return RNG.integers(0, 65536, (height, width), dtype=np.uint16)
    depth = RNG.uniform(0.2, 5.0, (height, width)).astype(np.float32)
    depth[0, 0] = np.nan
    return depth


def random_pose(seed: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = np.random.default_rng(seed).uniform(-2, 2, 3)
    return T


INTRINSICS = CameraIntrinsics(
    width=64,
    height=48,
    K=np.array([[60.5, 0.0, 31.5], [0.0, 61.25, 23.5], [0.0, 0.0, 1.0]]),
    D=np.array([-0.12, 0.03, 0.001, -0.002, 0.0005]),
)


# --- time ---------------------------------------------------------------------------------------


def test_stamps_convert_to_sec_nanosec_and_back(types):
    stamp = ns_to_stamp(types, STAMP)
    assert (stamp.sec, stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert stamp_to_ns(stamp) == STAMP


def test_negative_stamp_keeps_nanosec_in_range(types):
    stamp = ns_to_stamp(types, -1)
    assert (stamp.sec, stamp.nanosec) == (-1, 999_999_999)
    assert stamp_to_ns(stamp) == -1


def test_stamp_beyond_int32_seconds_raises_message_error(types):
    with pytest.raises(MessageError, match="header.stamp"):
        ns_to_stamp(types, 2**31 * 1_000_000_000)


# --- Image --------------------------------------------------------------------------------------


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8", "mono8", "mono16", "16UC1", "32FC1"])
def test_image_round_trips_exactly_in_each_encoding(types, encoding):
    pixels = sample_image(encoding)
    msg = image_to_msg(types, pixels, encoding, STAMP, "cam0_optical")
    assert (msg.height, msg.width, msg.encoding, msg.is_bigendian) == (5, 7, encoding, 0)
    assert msg.step == 7 * pixels.itemsize * (pixels.shape[2] if pixels.ndim == 3 else 1)
    assert stamp_to_ns(msg.header.stamp) == STAMP and msg.header.frame_id == "cam0_optical"
    back = image_from_msg(msg)
    assert back.dtype == pixels.dtype and back.shape == pixels.shape
    np.testing.assert_array_equal(back, pixels)


@pytest.mark.parametrize("encoding", ["rgb8", "mono8", "mono16", "32FC1"])
def test_image_with_padded_rows_round_trips(types, encoding):
    pixels = sample_image(encoding)
    row_bytes = pixels[0].nbytes
    msg = image_to_msg(types, pixels, encoding, STAMP, "c", step=row_bytes + 5)
    assert msg.step == row_bytes + 5 and len(msg.data) == (row_bytes + 5) * 5
    np.testing.assert_array_equal(image_from_msg(msg), pixels)


@pytest.mark.parametrize("encoding", ["mono16", "32FC1"])
def test_big_endian_image_stores_big_endian_bytes_and_round_trips(types, encoding):
    pixels = sample_image(encoding)
    msg = image_to_msg(
        types, pixels, encoding, STAMP, "c", step=pixels[0].nbytes + 3, is_bigendian=True
    )
    first = bytes(memoryview(msg.data)[: pixels.itemsize])
    assert first == np.asarray(pixels[0, :1], dtype=pixels.dtype.newbyteorder(">")).tobytes()
    back = image_from_msg(msg)
    assert back.dtype.isnative
    np.testing.assert_array_equal(back, pixels)


def test_image_from_msg_reads_a_hand_made_big_endian_padded_layout(types):
    # 2x2 mono16, rows of 4 pixel bytes + 2 padding bytes, big-endian values 0x0102 ... 0x0708.
    data = bytes([1, 2, 3, 4, 0xEE, 0xEE, 5, 6, 7, 8, 0xEE, 0xEE])
    msg = types.get("sensor_msgs/msg/Image")(
        header=types.get("std_msgs/msg/Header")(stamp=ns_to_stamp(types, 0), frame_id=""),
        height=2,
        width=2,
        encoding="mono16",
        is_bigendian=1,
        step=6,
        data=types.to_bytes_field(np.frombuffer(data, np.uint8)),
    )
    np.testing.assert_array_equal(image_from_msg(msg), [[0x0102, 0x0304], [0x0506, 0x0708]])


def test_uint8_fields_use_the_fast_container_of_each_kind(types):
    msg = image_to_msg(types, sample_image("rgb8"), "rgb8", STAMP, "c")
    expected = np.ndarray if types.name == "rosbags" else array.array
    assert isinstance(msg.data, expected)


@pytest.mark.parametrize("encoding", ["rgb16", "8UC3", "yuv422"])
def test_unsupported_encoding_raises_message_error_naming_it(types, encoding):
    with pytest.raises(MessageError, match=f"Image.encoding: unsupported '{encoding}'"):
        image_to_msg(types, sample_image("rgb8"), encoding, STAMP, "c")
    msg = image_to_msg(types, sample_image("rgb8"), "rgb8", STAMP, "c")
    msg.encoding = encoding
    with pytest.raises(MessageError, match=encoding):
        image_from_msg(msg)


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8"])
def test_a_camera_colour_image_reads_as_rgb_whatever_its_channel_order(types, encoding):
    rgb = sample_image("rgb8")
    stored = {"rgb8": rgb, "bgr8": rgb[..., ::-1], "rgba8": np.dstack([rgb, rgb[..., :1]]),
              "bgra8": np.dstack([rgb[..., ::-1], rgb[..., :1]])}[encoding]
    msg = image_to_msg(types, np.ascontiguousarray(stored), encoding, STAMP, "c")
    back = camera_image_from_msg("rgb", msg)
    assert back.dtype == np.uint8 and back.flags.c_contiguous
    np.testing.assert_array_equal(back, rgb)


def test_a_millimetre_depth_image_reads_as_metres_with_zero_as_no_return(types):
    millimetres = np.array([[0, 1, 2500], [65535, 400, 0]], np.uint16)
    back = camera_image_from_msg("depth", image_to_msg(types, millimetres, "16UC1", STAMP, "c"))
    assert back.dtype == np.float32
    np.testing.assert_array_equal(np.isnan(back), millimetres == 0)
    np.testing.assert_allclose(back[millimetres > 0], millimetres[millimetres > 0] / 1000.0, rtol=1e-6)
    metres = sample_image("32FC1")
    read = camera_image_from_msg("depth", image_to_msg(types, metres, "32FC1", STAMP, "c"))
    np.testing.assert_array_equal(read, metres)


@pytest.mark.parametrize(("kind", "encoding"), [("rgb", "mono8"), ("mask", "16UC1"), ("depth", "mono16")])
def test_a_camera_image_in_another_kinds_encoding_raises_message_error_naming_both(types, kind, encoding):
    msg = image_to_msg(types, sample_image(encoding), encoding, STAMP, "c")
    with pytest.raises(MessageError, match=f"'{encoding}' for a {kind} image"):
        camera_image_from_msg(kind, msg)


@pytest.mark.parametrize(
    ("encoding", "pixels"),
    [
        ("mono8", np.zeros((4, 4), np.uint16)),
        ("mono16", np.zeros((4, 4), np.uint8)),
        ("rgb8", np.zeros((4, 4), np.uint8)),
        ("rgb8", np.zeros((4, 4, 4), np.uint8)),
        ("32FC1", np.zeros((4, 4), np.float64)),
        ("mono8", np.zeros((4, 4, 3), np.uint8)),
    ],
)
def test_array_not_matching_encoding_raises_message_error(types, encoding, pixels):
    with pytest.raises(MessageError, match=rf"Image.data: encoding {encoding} needs .* got shape"):
        image_to_msg(types, pixels, encoding, STAMP, "c")


def test_data_shorter_than_step_times_height_raises_message_error(types):
    msg = image_to_msg(types, sample_image("mono16"), "mono16", STAMP, "c")
    msg.data = types.to_bytes_field(np.zeros(5 * 14 - 1, np.uint8))
    with pytest.raises(MessageError, match=r"69 bytes, expected at least step \* height = 70"):
        image_from_msg(msg)


def test_step_smaller_than_a_row_raises_message_error(types):
    msg = image_to_msg(types, sample_image("rgb8"), "rgb8", STAMP, "c")
    msg.step = 20
    with pytest.raises(MessageError, match="Image.step: 20 < width"):
        image_from_msg(msg)
    with pytest.raises(MessageError, match="Image.step: 20 < width"):
        image_to_msg(types, sample_image("rgb8"), "rgb8", STAMP, "c", step=20)


# --- CameraInfo ---------------------------------------------------------------------------------


def test_camera_info_round_trips_and_fills_r_and_p_consistently(types):
    msg = camera_info_to_msg(types, INTRINSICS, STAMP, "cam0_optical")
    np.testing.assert_array_equal(np.reshape(msg.r, (3, 3)), np.eye(3))
    np.testing.assert_array_equal(
        np.reshape(msg.p, (3, 4)), np.hstack([INTRINSICS.K, [[0], [0], [0]]])
    )
    back = camera_info_from_msg(msg)
    assert (back.width, back.height, back.distortion_model) == (64, 48, "plumb_bob")
    np.testing.assert_array_equal(back.K, INTRINSICS.K)
    np.testing.assert_array_equal(back.D, INTRINSICS.D)


def test_uncalibrated_camera_info_raises_message_error(types):
    msg = camera_info_to_msg(types, INTRINSICS, STAMP, "c")
    msg.k = np.zeros(9)
    with pytest.raises(MessageError, match="uncalibrated"):
        camera_info_from_msg(msg)


def test_projection_matches_opencv_with_plumb_bob_distortion():
    points = np.random.default_rng(3).uniform([-0.5, -0.4, 1.0], [0.5, 0.4, 3.0], (50, 3))
    expected, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), INTRINSICS.K, INTRINSICS.D)
    np.testing.assert_allclose(INTRINSICS.project(points), expected[:, 0], atol=1e-9)


def test_points_behind_the_camera_project_to_nan():
    assert np.isnan(INTRINSICS.project(np.array([[0.1, 0.0, -1.0]]))).all()


# --- PointCloud2 --------------------------------------------------------------------------------


def test_pointcloud_round_trips_with_extra_fields(types):
    xyz = RNG.normal(size=(40, 3)).astype(np.float32)
    ids = RNG.integers(1, 65536, 40)
    extra = {"t": RNG.uniform(0, 2, 40), "volume": RNG.uniform(0, 1e-6, 40), "material": ids % 4}
    msg = pointcloud_to_msg(types, xyz, ids, STAMP, "world", fields=extra)
    assert [f.name for f in msg.fields] == ["x", "y", "z", "object_id", "t", "volume", "material"]
    assert msg.point_step % 4 == 0 and msg.row_step == 40 * msg.point_step
    cloud = pointcloud_from_msg(msg)
    assert (cloud.stamp_ns, cloud.frame_id) == (STAMP, "world")
    np.testing.assert_array_equal(cloud.xyz, xyz)
    assert cloud.object_id.dtype == np.uint16
    np.testing.assert_array_equal(cloud.object_id, ids)
    assert set(cloud.fields) == {"t", "volume", "material"}
    np.testing.assert_array_equal(cloud.fields["t"], extra["t"].astype(np.float32))
    np.testing.assert_array_equal(cloud.fields["volume"], extra["volume"].astype(np.float32))
    assert cloud.fields["material"].dtype == np.uint8
    np.testing.assert_array_equal(cloud.fields["material"], ids % 4)


def test_pointcloud_round_trips_without_extra_fields(types):
    xyz = RNG.normal(size=(9, 3))
    cloud = pointcloud_from_msg(pointcloud_to_msg(types, xyz, np.arange(9), STAMP))
    np.testing.assert_array_equal(cloud.xyz, xyz.astype(np.float32))
    np.testing.assert_array_equal(cloud.object_id, np.arange(9))
    assert cloud.fields == {} and cloud.frame_id == "world"


def test_a_cloud_with_a_non_finite_value_is_a_malformed_message(types):
    xyz = RNG.normal(size=(9, 3))
    xyz[[2, 5], 1] = np.nan  # the pipeline's clouds are dense: NaN is not "no point" there
    with pytest.raises(MessageError, match="PointCloud2 field 'y': 2 of 9 points are not finite"):
        pointcloud_from_msg(pointcloud_to_msg(types, xyz, np.arange(9), STAMP))
    sdf = np.zeros(9)
    sdf[0] = -np.inf
    with pytest.raises(MessageError, match="PointCloud2 field 'sdf': 1 of 9 points are not finite"):
        pointcloud_from_msg(pointcloud_to_msg(types, np.zeros((9, 3)), np.arange(9), STAMP, fields={"sdf": sdf}))


def test_empty_pointcloud_round_trips(types):
    msg = pointcloud_to_msg(types, np.zeros((0, 3)), np.zeros(0, int), STAMP, fields={"t": []})
    assert msg.width == 0 and len(msg.data) == 0
    cloud = pointcloud_from_msg(msg)
    assert cloud.xyz.shape == (0, 3) and cloud.object_id.shape == (0,)
    assert cloud.fields["t"].shape == (0,)


def hand_made_cloud(types, *, big_endian: bool, with_object_id: bool = True):
    """An organised 2x3 cloud in a foreign layout: other field order, float64, padding."""
    order = ">" if big_endian else "<"
    layout = {
        "object_id": (0, "u4", 6),
        "z": (4, "f4", 7),
        "y": (8, "f4", 7),
        "x": (12, "f4", 7),
        "intensity": (16, "f8", 8),
    }
    if not with_object_id:
        del layout["object_id"]
    record = np.dtype(
        {
            "names": list(layout),
            "formats": [order + v[1] for v in layout.values()],
            "offsets": [v[0] for v in layout.values()],
            "itemsize": 32,
        }
    )
    points = np.zeros(6, record)
    points["x"], points["y"], points["z"] = np.arange(6), 10 + np.arange(6), 20 + np.arange(6)
    points["intensity"] = np.linspace(0, 1, 6)
    if with_object_id:
        points["object_id"] = [1, 1, 2, 2, 3, 300]
    rows = np.zeros((2, 3 * 32 + 8), np.uint8)  # each row padded by 8 bytes
    rows[:, : 3 * 32] = points.view(np.uint8).reshape(2, 96)
    field = types.get("sensor_msgs/msg/PointField")
    return types.get("sensor_msgs/msg/PointCloud2")(
        header=types.get("std_msgs/msg/Header")(stamp=ns_to_stamp(types, STAMP), frame_id="map"),
        height=2,
        width=3,
        fields=[field(name=n, offset=v[0], datatype=v[2], count=1) for n, v in layout.items()],
        is_bigendian=big_endian,
        point_step=32,
        row_step=104,
        data=types.to_bytes_field(rows),
        is_dense=True,
    )


@pytest.mark.parametrize("big_endian", [False, True])
def test_pointcloud_from_msg_reads_any_field_order_padding_and_byte_order(types, big_endian):
    cloud = pointcloud_from_msg(hand_made_cloud(types, big_endian=big_endian))
    np.testing.assert_array_equal(cloud.xyz[:, 0], np.arange(6))
    np.testing.assert_array_equal(cloud.xyz[:, 1], 10 + np.arange(6))
    np.testing.assert_array_equal(cloud.xyz[:, 2], 20 + np.arange(6))
    np.testing.assert_array_equal(cloud.object_id, [1, 1, 2, 2, 3, 300])
    assert (
        cloud.fields["intensity"].dtype == np.float64 and cloud.fields["intensity"].dtype.isnative
    )
    np.testing.assert_array_equal(cloud.fields["intensity"], np.linspace(0, 1, 6))
    assert cloud.frame_id == "map"


def test_pointcloud_without_object_id_raises_message_error_naming_it(types):
    with pytest.raises(MessageError, match=r"missing \['object_id'\]"):
        pointcloud_from_msg(hand_made_cloud(types, big_endian=False, with_object_id=False))


def test_pointcloud_with_short_data_raises_message_error(types):
    msg = pointcloud_to_msg(types, np.zeros((4, 3)), np.ones(4), STAMP)
    msg.data = types.to_bytes_field(np.zeros(4 * msg.point_step - 1, np.uint8))
    with pytest.raises(MessageError, match="PointCloud2.data"):
        pointcloud_from_msg(msg)


@pytest.mark.parametrize("ids", [[-1, 2], [1, 65536], [1.5, 2]])
def test_object_ids_outside_uint16_raise_message_error(types, ids):
    with pytest.raises(MessageError, match="object_id"):
        pointcloud_to_msg(types, np.zeros((2, 3)), np.array(ids), STAMP)


def test_reserved_names_in_extra_fields_raise_message_error(types):
    with pytest.raises(MessageError, match="reserved"):
        pointcloud_to_msg(types, np.zeros((2, 3)), [1, 2], STAMP, fields={"object_id": [3, 4]})


# --- transforms and poses -----------------------------------------------------------------------


def test_transform_round_trips(types):
    T = random_pose(1)
    parent, child, back = transform_from_msg(transform_to_msg(types, "world", "cam0_optical", T, 5))
    assert (parent, child) == ("world", "cam0_optical")
    np.testing.assert_allclose(back, T, atol=1e-12)


def test_quaternion_is_written_in_ros_xyzw_order(types):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    q = transform_to_msg(types, "a", "b", T, 0).transform.rotation
    np.testing.assert_allclose([q.x, q.y, q.z, q.w], [0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-15)


def test_tf_message_carries_a_chain_of_transforms(types):
    if types.name == "rclpy" and not HAS_TF2_MSGS:
        pytest.skip("tf2_msgs Python package not installed")
    T_world_link, T_link_optical = random_pose(2), random_pose(3)
    msg = tf_message(
        types,
        [
            transform_to_msg(types, "world", "cam0_link", T_world_link, 1),
            transform_to_msg(types, "cam0_link", "cam0_optical", T_link_optical, 1),
        ],
    )
    chain = {child: (parent, T) for parent, child, T in map(transform_from_msg, msg.transforms)}
    parent, T_link = chain["cam0_optical"]
    assert parent == "cam0_link" and chain[parent][0] == "world"
    np.testing.assert_allclose(chain[parent][1] @ T_link, T_world_link @ T_link_optical, atol=1e-12)


def test_pose_stamped_round_trips(types):
    T = random_pose(4)
    msg = pose_stamped_to_msg(types, T, STAMP, "world")
    assert msg.header.frame_id == "world"
    stamp, back = pose_stamped_from_msg(msg)
    assert stamp == STAMP
    np.testing.assert_allclose(back, T, atol=1e-12)


@pytest.mark.parametrize("bad", [np.diag([2.0, 1, 1, 1]), np.diag([-1.0, 1, 1, 1]), np.eye(3)])
def test_non_rigid_matrix_raises_message_error(types, bad):
    with pytest.raises(MessageError, match="transform world -> x"):
        transform_to_msg(types, "world", "x", bad, 0)


def test_zero_quaternion_raises_message_error(types):
    msg = pose_stamped_to_msg(types, np.eye(4), 0, "world")
    msg.pose.orientation.w = 0.0
    with pytest.raises(MessageError, match="invalid quaternion"):
        pose_stamped_from_msg(msg)


# --- the two kinds of message classes on the wire -----------------------------------------------


def wire_cases(types):
    return {
        "sensor_msgs/msg/Image": image_to_msg(
            types,
            np.arange(35, dtype=np.uint16).reshape(5, 7) * 1000,
            "mono16",
            STAMP,
            "c",
            step=16,
            is_bigendian=True,
        ),
        "sensor_msgs/msg/CameraInfo": camera_info_to_msg(types, INTRINSICS, STAMP, "c"),
        "sensor_msgs/msg/PointCloud2": pointcloud_to_msg(
            types, np.arange(12.0).reshape(4, 3), [1, 2, 3, 4], STAMP, fields={"t": np.ones(4)}
        ),
        "geometry_msgs/msg/TransformStamped": transform_to_msg(types, "w", "c", random_pose(5), 9),
        "geometry_msgs/msg/PoseStamped": pose_stamped_to_msg(types, random_pose(6), STAMP, "w"),
    }


def read_cloud(msg) -> tuple:
    cloud = pointcloud_from_msg(msg)
    return cloud.xyz, cloud.object_id, cloud.fields["t"], cloud.stamp_ns


def read_info(msg) -> tuple:
    info = camera_info_from_msg(msg)
    return info.K, info.D, info.width, info.height


READERS = {  # message type -> what our readers make of it, as a tuple
    "sensor_msgs/msg/Image": lambda m: (image_from_msg(m), stamp_to_ns(m.header.stamp)),
    "sensor_msgs/msg/CameraInfo": read_info,
    "sensor_msgs/msg/PointCloud2": read_cloud,
    "geometry_msgs/msg/TransformStamped": transform_from_msg,
    "geometry_msgs/msg/PoseStamped": pose_stamped_from_msg,
}


@pytest.mark.parametrize("msgtype", sorted(READERS))
def test_rclpy_and_rosbags_messages_read_the_same_after_crossing_the_wire(msgtype):
    serialization = pytest.importorskip("rclpy.serialization")
    store = jazzy_typestore()
    rclpy_msg = wire_cases(rclpy_types())[msgtype]
    rosbags_msg = wire_cases(rosbags_types())[msgtype]
    from_rclpy = store.deserialize_cdr(serialization.serialize_message(rclpy_msg), msgtype)
    from_rosbags = serialization.deserialize_message(
        bytes(store.serialize_cdr(rosbags_msg, msgtype)), type(rclpy_msg)
    )
    expected = READERS[msgtype](rosbags_msg)
    for got in (READERS[msgtype](from_rclpy), READERS[msgtype](from_rosbags)):
        for value, want in zip(got, expected, strict=True):
            np.testing.assert_array_equal(value, want)
