"""numpy <-> ROS 2 message conversion, one implementation for two kinds of message classes.

What it is for: building and reading sensor_msgs Image / CameraInfo / PointCloud2,
geometry_msgs TransformStamped / PoseStamped and tf2_msgs TFMessage from numpy arrays, with the
message classes of either ``rosbags`` (bag files, no ROS needed) or the ROS 2 Python message
packages (what rclpy publishes). The caller picks the classes with a ``MessageTypes`` provider:
``rosbags_types()`` or ``rclpy_types()``. Reading accepts messages of either kind.
What it is not for: bag files (``mosiv_ros.io.bag``), publishing, QoS. This module never imports
rclpy itself (``rclpy_types`` imports only the message packages such as ``sensor_msgs.msg``).

Conventions: stamps are int nanoseconds; poses are 4x4 float64 homogeneous matrices
``T_parent_child`` mapping child coordinates to parent; ROS quaternions are (x, y, z, w), which is
also scipy's order. Malformed input raises ``MessageError`` naming the field.
"""

from __future__ import annotations

import array
import functools
import importlib
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore
from scipy.spatial.transform import Rotation

from mosiv_ros.io.errors import MessageError
from mosiv_ros.io.recording import CameraIntrinsics, PointCloud

ENCODINGS: dict[str, tuple[np.dtype, int]] = {
    "rgb8": (np.dtype(np.uint8), 3),
    "bgr8": (np.dtype(np.uint8), 3),
    "rgba8": (np.dtype(np.uint8), 4),
    "bgra8": (np.dtype(np.uint8), 4),
    "mono8": (np.dtype(np.uint8), 1),
    "mono16": (np.dtype(np.uint16), 1),
    "16UC1": (np.dtype(np.uint16), 1),
    "32FC1": (np.dtype(np.float32), 1),
}
"""Supported image encodings: name -> (pixel channel dtype, channels)."""
CAMERA_IMAGE_ENCODINGS: dict[str, tuple[str, ...]] = {
    "rgb": ("rgb8", "bgr8", "rgba8", "bgra8"),
    "mask": ("mono8", "mono16"),
    "depth": ("32FC1", "16UC1"),
}
"""Encodings a camera's colour image, instance mask and depth image may come in (depth as in
REP 118: 32FC1 metres, or 16UC1 millimetres with 0 for no return)."""

POINT_FIELD_DTYPES: dict[int, np.dtype] = {
    1: np.dtype(np.int8),
    2: np.dtype(np.uint8),
    3: np.dtype(np.int16),
    4: np.dtype(np.uint16),
    5: np.dtype(np.int32),
    6: np.dtype(np.uint32),
    7: np.dtype(np.float32),
    8: np.dtype(np.float64),
}
"""sensor_msgs/PointField datatype constants (INT8 .. FLOAT64) -> numpy dtype."""
_POINT_FIELD_CODES = {dtype: code for code, dtype in POINT_FIELD_DTYPES.items()}
INTEGER_CLOUD_FIELDS: dict[str, np.dtype] = {
    "object_id": np.dtype(np.uint16),
    "material": np.dtype(np.uint8),
    "segment": np.dtype(np.uint16),
    "rgb": np.dtype(np.uint32),
    "track_id": np.dtype(np.uint32),
    "cut": np.dtype(np.uint8),
}
"""PointCloud2 fields written as unsigned integers."""
FLOAT64_CLOUD_FIELDS = ("boundary_beta", "boundary_eps")
"""PointCloud2 fields written as float64: settings a consumer must read back exactly (every other
extra field is float32)."""
_CLOUD_REQUIRED = ("x", "y", "z", "object_id")
_PADDING_FIELDS = ("", "_")  # unnamed padding, as some point-cloud tools write it


class MessageTypes:
    """Provider of message classes and of the value a ``uint8[]`` field wants.

    Use ``rosbags_types()`` or ``rclpy_types()``; messages are always built with keyword
    arguments for every field, which both kinds of classes accept.
    """

    def __init__(
        self,
        name: str,
        lookup: Callable[[str], type],
        bytes_field: Callable[[np.ndarray], Any],
    ) -> None:
        self.name = name
        self._lookup = lookup
        self._bytes_field = bytes_field
        self._classes: dict[str, type] = {}

    def __repr__(self) -> str:
        return f"MessageTypes({self.name!r})"

    def get(self, name: str) -> type:
        """The message class of ``name``, e.g. ``'sensor_msgs/msg/Image'``."""
        if name not in self._classes:
            self._classes[name] = self._lookup(name)
        return self._classes[name]

    def to_bytes_field(self, arr: np.ndarray) -> Any:
        """The raw bytes of ``arr`` (C order) in the form a ``uint8[]`` field of this kind wants."""
        return self._bytes_field(np.ascontiguousarray(arr).reshape(-1).view(np.uint8))


@functools.cache
def jazzy_typestore() -> Typestore:
    """The rosbags typestore of ROS 2 Jazzy, built once per process."""
    return get_typestore(Stores.ROS2_JAZZY)


def rosbags_types(typestore: Typestore | None = None) -> MessageTypes:
    """Message classes of a rosbags typestore (default: ``jazzy_typestore()``)."""
    store = jazzy_typestore() if typestore is None else typestore

    def lookup(name: str) -> type:
        try:
            return store.types[name]
        except KeyError:
            raise KeyError(f"message type {name!r} is not in the rosbags typestore") from None

    return MessageTypes("rosbags", lookup, lambda data: data.copy())


def _import_message_class(name: str) -> type:
    package, kind, cls = name.split("/")
    return getattr(importlib.import_module(f"{package}.{kind}"), cls)


def rclpy_types() -> MessageTypes:
    """Message classes of the ROS 2 Python message packages (``sensor_msgs.msg`` ...).

    ``uint8[]`` fields get an ``array.array('B')``: anything else makes the generated classes
    check every element in Python, which is very slow for images.
    """
    return MessageTypes(
        "rclpy", _import_message_class, lambda data: array.array("B", data.tobytes())
    )


def _bytes_of(data: Any) -> np.ndarray:
    """A uint8 view of a ``uint8[]`` field of either kind (numpy array, bytes, array.array)."""
    return np.frombuffer(memoryview(data), dtype=np.uint8)


# --- time and header ---------------------------------------------------------------------------


def stamp_to_ns(stamp: Any) -> int:
    """Nanoseconds of a builtin_interfaces/Time."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(types: MessageTypes, ns: int) -> Any:
    """builtin_interfaces/Time of ``ns`` nanoseconds (sec is int32, nanosec in 0..1e9-1)."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    if not -(2**31) <= sec < 2**31:
        raise MessageError(f"header.stamp: {ns} ns does not fit builtin_interfaces/Time")
    return types.get("builtin_interfaces/msg/Time")(sec=sec, nanosec=nanosec)


def make_header(types: MessageTypes, stamp_ns: int, frame_id: str) -> Any:
    """std_msgs/Header with the given stamp and frame."""
    return types.get("std_msgs/msg/Header")(stamp=ns_to_stamp(types, stamp_ns), frame_id=frame_id)


# --- sensor_msgs/Image -------------------------------------------------------------------------


def _encoding(encoding: str) -> tuple[np.dtype, int]:
    try:
        return ENCODINGS[encoding]
    except KeyError:
        raise MessageError(
            f"Image.encoding: unsupported {encoding!r} (expected one of {', '.join(ENCODINGS)})"
        ) from None


def image_to_msg(
    types: MessageTypes,
    array: np.ndarray,
    encoding: str,
    stamp_ns: int,
    frame_id: str,
    *,
    step: int | None = None,
    is_bigendian: bool = False,
) -> Any:
    """sensor_msgs/Image of ``array`` in ``encoding`` (one of ``ENCODINGS``).

    ``step`` (bytes per row, default: no padding) and ``is_bigendian`` choose the layout; the
    array's dtype and shape must match the encoding exactly (no silent casts).
    """
    dtype, channels = _encoding(encoding)
    array = np.asarray(array)
    shape_ok = array.ndim == 2 if channels == 1 else array.ndim == 3 and array.shape[2] == channels
    if array.dtype != dtype or not shape_ok:
        layout = "(H, W)" if channels == 1 else f"(H, W, {channels})"
        raise MessageError(
            f"Image.data: encoding {encoding} needs a {layout} {dtype} array, "
            f"got shape {array.shape} {array.dtype}"
        )
    height, width = array.shape[:2]
    row_bytes = width * channels * dtype.itemsize
    step = row_bytes if step is None else int(step)
    if step < row_bytes:
        raise MessageError(f"Image.step: {step} < width * bytes per pixel = {row_bytes}")
    ordered = np.ascontiguousarray(array, dtype=dtype.newbyteorder(">" if is_bigendian else "<"))
    rows = np.zeros((height, step), dtype=np.uint8)
    rows[:, :row_bytes] = ordered.view(np.uint8).reshape(height, row_bytes)
    return types.get("sensor_msgs/msg/Image")(
        header=make_header(types, stamp_ns, frame_id),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=int(is_bigendian),
        step=step,
        data=types.to_bytes_field(rows),
    )


def image_from_msg(msg: Any) -> np.ndarray:
    """The pixels of a sensor_msgs/Image as a native-order array owning its memory.

    As stored, channels in the encoding's order: rgb8 and bgr8 -> (H, W, 3) uint8, rgba8 and
    bgra8 -> (H, W, 4) uint8, mono8 -> (H, W) uint8, mono16 and 16UC1 -> (H, W) uint16, 32FC1 ->
    (H, W) float32; row padding (``step``) and ``is_bigendian`` are honoured
    (``camera_image_from_msg`` makes a camera's images RGB and metres).
    """
    dtype, channels = _encoding(msg.encoding)
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = width * channels * dtype.itemsize
    if step < row_bytes:
        raise MessageError(
            f"Image.step: {step} < width * bytes per pixel = {row_bytes} ({msg.encoding})"
        )
    data = _bytes_of(msg.data)
    if data.size < step * height:
        raise MessageError(
            f"Image.data: {data.size} bytes, expected at least step * height = {step * height}"
        )
    rows = np.ascontiguousarray(data[: step * height].reshape(height, step)[:, :row_bytes])
    pixels = rows.view(dtype.newbyteorder(">" if msg.is_bigendian else "<")).astype(dtype)
    return pixels.reshape((height, width) if channels == 1 else (height, width, channels))


def camera_image_from_msg(kind: str, msg: Any) -> np.ndarray:
    """A camera's ``kind`` image ("rgb", "mask" or "depth") as the pipeline takes it.

    Colour -> (H, W, 3) uint8 RGB (from rgb8, bgr8, rgba8 or bgra8; alpha dropped); mask ->
    (H, W) uint8 or uint16 ids; depth -> (H, W) float32 metres, NaN = no return (from 32FC1, or
    16UC1 millimetres whose 0 means no return). MessageError for another encoding.
    """
    allowed = CAMERA_IMAGE_ENCODINGS[kind]
    if msg.encoding not in allowed:
        raise MessageError(f"Image.encoding: {msg.encoding!r} for a {kind} image, expected one of {allowed}")
    pixels = image_from_msg(msg)
    if msg.encoding == "16UC1":
        return np.where(pixels > 0, pixels.astype(np.float32) * np.float32(1e-3), np.float32(np.nan))
    if msg.encoding in ("bgr8", "bgra8"):
        return np.ascontiguousarray(pixels[..., 2::-1])
    if msg.encoding == "rgba8":
        return np.ascontiguousarray(pixels[..., :3])
    return pixels


# --- sensor_msgs/CameraInfo --------------------------------------------------------------------


def camera_info_to_msg(
    types: MessageTypes, intrinsics: CameraIntrinsics, stamp_ns: int, frame_id: str
) -> Any:
    """sensor_msgs/CameraInfo of ``intrinsics``: R = identity, P = [K | 0], no binning or ROI."""
    K = intrinsics.K
    roi = types.get("sensor_msgs/msg/RegionOfInterest")(
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    return types.get("sensor_msgs/msg/CameraInfo")(
        header=make_header(types, stamp_ns, frame_id),
        height=intrinsics.height,
        width=intrinsics.width,
        distortion_model=intrinsics.distortion_model,
        d=np.array(intrinsics.D, dtype=np.float64),
        k=K.ravel().copy(),
        r=np.eye(3).ravel(),
        p=np.hstack([K, np.zeros((3, 1))]).ravel(),
        binning_x=0,
        binning_y=0,
        roi=roi,
    )


def camera_info_from_msg(msg: Any) -> CameraIntrinsics:
    """CameraIntrinsics of a calibrated, full-resolution sensor_msgs/CameraInfo."""
    K = np.array(msg.k, dtype=np.float64)
    if K.size != 9:
        raise MessageError(f"CameraInfo.k: expected 9 values, got {K.size}")
    K = K.reshape(3, 3)
    if K[2, 2] == 0:
        raise MessageError("CameraInfo.k: the camera is uncalibrated (K[2][2] is 0)")
    if max(int(msg.binning_x), int(msg.binning_y)) > 1:
        raise MessageError(
            f"CameraInfo.binning: {msg.binning_x}x{msg.binning_y} binning is not supported"
        )
    if msg.roi.width or msg.roi.height:
        raise MessageError("CameraInfo.roi: a region of interest is not supported")
    try:
        return CameraIntrinsics(
            width=int(msg.width),
            height=int(msg.height),
            K=K,
            D=np.array(msg.d, dtype=np.float64),
            distortion_model=str(msg.distortion_model),
        )
    except ValueError as exc:
        raise MessageError(f"CameraInfo: {exc}") from None


# --- sensor_msgs/PointCloud2 -------------------------------------------------------------------


def _as_integers(values: np.ndarray, dtype: np.dtype, what: str) -> np.ndarray:
    """``values`` as ``dtype`` if they are whole numbers in its range, else MessageError."""
    info = np.iinfo(dtype)
    if values.size:
        whole = values.dtype.kind in "biu" or bool(np.all(np.mod(values, 1) == 0))
        if not whole or values.min() < info.min or values.max() > info.max:
            raise MessageError(
                f"{what}: expected whole numbers in {info.min}..{info.max}, "
                f"got values in {values.min()}..{values.max()} ({values.dtype})"
            )
    return values.astype(dtype)


def pointcloud_to_msg(
    types: MessageTypes,
    xyz: np.ndarray,
    object_id: np.ndarray,
    stamp_ns: int,
    frame_id: str = "world",
    fields: Mapping[str, np.ndarray] | None = None,
) -> Any:
    """sensor_msgs/PointCloud2 (height 1, little-endian) of N points.

    Fields: x, y, z float32; object_id uint16; then each entry of ``fields`` as float32, except
    the integer fields of ``INTEGER_CLOUD_FIELDS`` (``material`` uint8, ``segment`` uint16, ``rgb``
    and ``track_id`` uint32) and
    the float64 ones of ``FLOAT64_CLOUD_FIELDS``, in the given order, each aligned to its size.
    """
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise MessageError(f"PointCloud2 x, y, z: expected an (N, 3) array, got shape {xyz.shape}")
    n = len(xyz)
    columns: list[tuple[str, np.dtype, np.ndarray]] = [
        ("x", np.dtype(np.float32), xyz[:, 0]),
        ("y", np.dtype(np.float32), xyz[:, 1]),
        ("z", np.dtype(np.float32), xyz[:, 2]),
    ]
    fields = dict(fields or {})
    reserved = [name for name in _CLOUD_REQUIRED if name in fields]
    if reserved:
        raise MessageError(f"PointCloud2 fields {reserved}: reserved, pass them as xyz / object_id")
    for name, values in {"object_id": object_id, **fields}.items():
        values = np.asarray(values)
        if values.shape != (n,):
            raise MessageError(
                f"PointCloud2 field {name!r}: expected shape ({n},), got {values.shape}"
            )
        if name in INTEGER_CLOUD_FIELDS:
            dtype = INTEGER_CLOUD_FIELDS[name]
            columns.append(
                (name, dtype, _as_integers(values, dtype, f"PointCloud2 field {name!r}"))
            )
        else:
            dtype = np.dtype(np.float64 if name in FLOAT64_CLOUD_FIELDS else np.float32)
            columns.append((name, dtype, values))

    offsets, offset = [], 0
    for _, dtype, _ in columns:
        offset = -(-offset // dtype.itemsize) * dtype.itemsize
        offsets.append(offset)
        offset += dtype.itemsize
    point_step = -(-offset // 4) * 4
    record = np.dtype(
        {
            "names": [name for name, _, _ in columns],
            "formats": [dtype.newbyteorder("<") for _, dtype, _ in columns],
            "offsets": offsets,
            "itemsize": point_step,
        }
    )
    points = np.zeros(n, dtype=record)
    for name, _, values in columns:
        points[name] = values

    point_field = types.get("sensor_msgs/msg/PointField")
    return types.get("sensor_msgs/msg/PointCloud2")(
        header=make_header(types, stamp_ns, frame_id),
        height=1,
        width=n,
        fields=[
            point_field(name=name, offset=off, datatype=_POINT_FIELD_CODES[dtype], count=1)
            for (name, dtype, _), off in zip(columns, offsets, strict=True)
        ],
        is_bigendian=False,
        point_step=point_step,
        row_step=point_step * n,
        data=types.to_bytes_field(points),
        is_dense=bool(np.isfinite(xyz).all()),
    )


def _cloud_record_dtype(msg: Any) -> np.dtype:
    """Structured dtype of one point of ``msg``, from its field list and point_step."""
    order = ">" if msg.is_bigendian else "<"
    point_step = int(msg.point_step)
    names, formats, offsets = [], [], []
    for index, fld in enumerate(msg.fields):
        if fld.name in _PADDING_FIELDS:
            continue
        where = f"PointCloud2.fields[{index}] ({fld.name!r})"
        if fld.name in names:
            raise MessageError(f"{where}: duplicate field name")
        if int(fld.datatype) not in POINT_FIELD_DTYPES:
            raise MessageError(f"{where}: unknown datatype {fld.datatype}")
        base = POINT_FIELD_DTYPES[int(fld.datatype)].newbyteorder(order)
        count = max(1, int(fld.count))
        if int(fld.offset) + base.itemsize * count > point_step:
            raise MessageError(
                f"{where}: offset {fld.offset} + {count} x {base.itemsize} bytes exceeds "
                f"point_step {point_step}"
            )
        names.append(fld.name)
        formats.append(base if count == 1 else np.dtype((base, (count,))))
        offsets.append(int(fld.offset))
    missing = [name for name in _CLOUD_REQUIRED if name not in names]
    if missing:
        raise MessageError(f"PointCloud2.fields: missing {missing} (fields present: {names})")
    for name in _CLOUD_REQUIRED:
        if formats[names.index(name)].shape:
            raise MessageError(f"PointCloud2 field {name!r}: expected count 1")
    return np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step}
    )


def pointcloud_from_msg(msg: Any) -> PointCloud:
    """PointCloud of any sensor_msgs/PointCloud2 with x, y, z and an integer object_id field.

    Any field order, offsets, point/row padding, byte order and organised (height > 1) layout is
    read; extra fields keep their datatype (native byte order). The pipeline's clouds are dense:
    a NaN or infinite value in any floating-point field makes the message malformed.
    """
    record = _cloud_record_dtype(msg)
    height, width = int(msg.height), int(msg.width)
    row_bytes = width * record.itemsize
    if int(msg.row_step) < row_bytes:
        raise MessageError(
            f"PointCloud2.row_step: {msg.row_step} < width * point_step = {row_bytes}"
        )
    needed = int(msg.row_step) * height
    data = _bytes_of(msg.data)
    if data.size < needed:
        raise MessageError(
            f"PointCloud2.data: {data.size} bytes, expected at least row_step * height = {needed}"
        )
    rows = data[:needed].reshape(height, int(msg.row_step))[:, :row_bytes]
    points = np.ascontiguousarray(rows).reshape(-1).view(record)

    if (id_dtype := points["object_id"].dtype).kind not in "iu":
        raise MessageError(f"PointCloud2 field 'object_id': expected integers, got {id_dtype}")
    object_id = _as_integers(
        points["object_id"], np.dtype(np.uint16), "PointCloud2 field 'object_id'"
    )
    for name in record.names:
        if points[name].dtype.kind == "f" and not np.all(finite := np.isfinite(points[name])):
            raise MessageError(f"PointCloud2 field {name!r}: {int((~finite).sum())} of {len(points)} "
                               "points are not finite (NaN or infinite)")
    xyz = np.stack([points["x"], points["y"], points["z"]], axis=1).astype(np.float32)
    extra = {
        name: points[name].astype(points[name].dtype.newbyteorder("="))
        for name in record.names
        if name not in _CLOUD_REQUIRED
    }
    return PointCloud(
        xyz=xyz,
        object_id=object_id,
        fields=extra,
        stamp_ns=stamp_to_ns(msg.header.stamp),
        frame_id=str(msg.header.frame_id),
    )


# --- geometry_msgs / tf2_msgs ------------------------------------------------------------------


def _translation_quaternion(T: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """(translation, quaternion xyzw) of a rigid 4x4 transform; MessageError if it is not one."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise MessageError(f"{what}: expected a 4x4 matrix, got shape {T.shape}")
    R = T[:3, :3]
    rigid = (
        np.allclose(T[3], [0.0, 0.0, 0.0, 1.0])
        and np.allclose(R.T @ R, np.eye(3), atol=1e-6)
        and np.linalg.det(R) > 0
    )
    if not rigid or not np.all(np.isfinite(T)):
        raise MessageError(f"{what}: not a rigid transform (rotation + translation)")
    return T[:3, 3].copy(), Rotation.from_matrix(R).as_quat()


def _matrix(translation: Any, rotation: Any, what: str) -> np.ndarray:
    """4x4 transform of a geometry_msgs translation/position and quaternion."""
    q = np.array([rotation.x, rotation.y, rotation.z, rotation.w], dtype=np.float64)
    norm = np.linalg.norm(q)
    if not np.isfinite(norm) or norm < 1e-9:
        raise MessageError(f"{what}: invalid quaternion {q.tolist()} (x, y, z, w)")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q / norm).as_matrix()
    T[:3, 3] = [translation.x, translation.y, translation.z]
    return T


def transform_to_msg(
    types: MessageTypes, parent: str, child: str, T: np.ndarray, stamp_ns: int
) -> Any:
    """geometry_msgs/TransformStamped of ``T`` = T_parent_child (child -> parent coordinates)."""
    t, q = _translation_quaternion(T, f"transform {parent} -> {child}")
    transform = types.get("geometry_msgs/msg/Transform")(
        translation=types.get("geometry_msgs/msg/Vector3")(
            x=float(t[0]), y=float(t[1]), z=float(t[2])
        ),
        rotation=types.get("geometry_msgs/msg/Quaternion")(
            x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
        ),
    )
    return types.get("geometry_msgs/msg/TransformStamped")(
        header=make_header(types, stamp_ns, parent), child_frame_id=child, transform=transform
    )


def transform_from_msg(msg: Any) -> tuple[str, str, np.ndarray]:
    """(parent, child, T_parent_child) of a geometry_msgs/TransformStamped."""
    parent, child = str(msg.header.frame_id), str(msg.child_frame_id)
    what = f"TransformStamped {parent} -> {child}"
    return parent, child, _matrix(msg.transform.translation, msg.transform.rotation, what)


def tf_message(types: MessageTypes, transforms: Iterable[Any]) -> Any:
    """tf2_msgs/TFMessage holding ``transforms`` (TransformStamped messages)."""
    return types.get("tf2_msgs/msg/TFMessage")(transforms=list(transforms))


def pose_stamped_to_msg(types: MessageTypes, T: np.ndarray, stamp_ns: int, frame_id: str) -> Any:
    """geometry_msgs/PoseStamped of the pose ``T`` (body -> ``frame_id`` coordinates)."""
    t, q = _translation_quaternion(T, "PoseStamped.pose")
    pose = types.get("geometry_msgs/msg/Pose")(
        position=types.get("geometry_msgs/msg/Point")(x=float(t[0]), y=float(t[1]), z=float(t[2])),
        orientation=types.get("geometry_msgs/msg/Quaternion")(
            x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
        ),
    )
    return types.get("geometry_msgs/msg/PoseStamped")(
        header=make_header(types, stamp_ns, frame_id), pose=pose
    )


def pose_stamped_from_msg(msg: Any) -> tuple[int, np.ndarray]:
    """(stamp_ns, T) of a geometry_msgs/PoseStamped; the frame is ``msg.header.frame_id``."""
    T = _matrix(msg.pose.position, msg.pose.orientation, "PoseStamped.pose")
    return stamp_to_ns(msg.header.stamp), T
