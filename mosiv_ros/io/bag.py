"""rosbag2 recordings in the DESIGN.md layout, read and written with rosbags (no ROS needed).

What it is for: ``read_recording`` / ``write_recording`` between a bag directory (MCAP or sqlite3)
and an in-memory ``Recording``; ``iter_raw_messages`` / ``list_topics`` for replaying a bag's
serialized CDR messages unchanged; ``read_custom_data`` for its metadata; ``load_scene`` for a
scene declaration from a bag, a file or inline text (the nodes' ``scene`` parameter; here, above
``io.scene``, because a bag's declaration is read from its metadata); ``find_bags`` for the bags
under directories (``mosiv batch``). Every problem with a bag
is raised as ``BagError`` naming the bag, the topic and the problem; errors of the storage
libraries are wrapped here, at the boundary.
What it is not for: live topics, message conversion (``mosiv_ros.io.messages``), scene schema
(``mosiv_ros.io.scene``).

Layout, per camera ``<cam>``: ``/<cam>/color/image_raw`` (rgb8; bgr8, rgba8, bgra8 read too),
``/<cam>/color/camera_info``, ``/<cam>/instance_mask`` (mono8/mono16), optional
``/<cam>/depth/image_rect`` (32FC1 metres; 16UC1 millimetres read too; written: rgb8, 32FC1); plus
``/tf_static`` and optional ``/gripper/pose``. Reading rules:

- cameras are discovered from those topic names; other topics are ignored;
- a camera's image, mask and depth are paired by *exact* header stamp (by
  ``streams.CameraFrameAssembler``, the rule live nodes use too): every image needs a mask with
  the same stamp and vice versa, and, when the depth topic exists, a depth image too;
- camera_info must exist and be constant; its stamps need not match the images';
- extrinsics come from ``/tf_static``: any chain of static transforms (either direction) from
  ``world`` to the images' ``header.frame_id`` (``<cam>_optical`` if empty);
- gripper poses are expressed in ``world`` through the same static transforms;
- the message count of each topic must match ``metadata.yaml`` (a truncated storage file is an
  error, never silently fewer frames);
- an MCAP chunk that carries a checksum must match it (``write_recording`` writes them,
  ``io.mcap``; a chunk without one, as in bags written before, is read unchecked).
"""

from __future__ import annotations

import logging
import re
import shutil
import sys
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import (
    CompressionFormat,
    CompressionMode,
    Reader,
    StoragePlugin,
    Writer,
    WriterError,
)

from mosiv_ros.io.errors import BagError, MessageError, SceneError, not_utf8, shown
from mosiv_ros.io.mcap import add_chunk_crcs, chunk_crcs
from mosiv_ros.io.messages import (
    CAMERA_IMAGE_ENCODINGS,
    camera_image_from_msg,
    camera_info_from_msg,
    camera_info_to_msg,
    image_to_msg,
    jazzy_typestore,
    pose_stamped_from_msg,
    pose_stamped_to_msg,
    rosbags_types,
    stamp_to_ns,
    tf_message,
    transform_from_msg,
    transform_to_msg,
)
from mosiv_ros.io.recording import Camera, CameraIntrinsics, Frame, Recording
from mosiv_ros.io.scene import SCENE_KEY, Scene, load_yaml, parse_scene, read_scene_text, scene_to_yaml
from mosiv_ros.io.streams import CameraFrameAssembler
from mosiv_ros.io.transforms import WORLD_FRAME, StaticTransforms

_LOG = logging.getLogger(__name__)

TF_STATIC_TOPIC = "/tf_static"
GRIPPER_POSE_TOPIC = "/gripper/pose"
STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"

_CAMERA_TOPIC = re.compile(
    r"^/(?P<camera>.+)/(?P<kind>color/image_raw|color/camera_info|instance_mask|depth/image_rect)$"
)
_KINDS = {  # topic suffix -> (attribute of CameraTopics, message type)
    "color/image_raw": ("color", IMAGE),
    "color/camera_info": ("camera_info", CAMERA_INFO),
    "instance_mask": ("mask", IMAGE),
    "depth/image_rect": ("depth", IMAGE),
}
_ASSEMBLER_KINDS = {"color": "rgb", "mask": "mask", "depth": "depth"}
"""Attribute of CameraTopics -> the image kind of ``CameraFrameAssembler`` and ``CAMERA_IMAGE_ENCODINGS``."""


@dataclass(frozen=True)
class CameraTopics:
    """Topic names of one camera in the DESIGN.md layout."""

    color: str
    camera_info: str
    mask: str
    depth: str


def camera_topics(camera: str) -> CameraTopics:
    """The topics of camera ``camera``, e.g. ``/cam0/color/image_raw``."""
    return CameraTopics(
        color=f"/{camera}/color/image_raw",
        camera_info=f"/{camera}/color/camera_info",
        mask=f"/{camera}/instance_mask",
        depth=f"/{camera}/depth/image_rect",
    )


@dataclass(frozen=True)
class RawMessage:
    """One stored message: serialized CDR exactly as in the bag (``publish(data)`` accepts it)."""

    topic: str
    msgtype: str
    log_time_ns: int
    data: bytes


@dataclass(frozen=True)
class TopicInfo:
    """A bag topic: its type, message count and offered QoS (latched = transient_local)."""

    name: str
    msgtype: str
    message_count: int
    latched: bool
    best_effort: bool


# --- reading: boundary with rosbags ------------------------------------------------------------


def _check_bag_dir(path: Path) -> None:
    if not path.exists():
        raise BagError(path, None, "does not exist")
    if not path.is_dir():
        raise BagError(path, None, "is a file, not a rosbag2 directory (with metadata.yaml)")
    if not (path / "metadata.yaml").is_file():
        raise BagError(path, None, "no metadata.yaml: not a rosbag2 directory")


def find_bags(paths: Iterable[str | Path]) -> list[Path]:
    """The rosbag2 directories among ``paths`` or below them (any depth), in order, each once.

    A path that is not a directory, or holds no bag, is a ``BagError``: a mistyped path is not
    an empty batch.
    """
    found: list[Path] = []
    for path in map(Path, paths):
        if not path.is_dir():
            raise BagError(path, None, "does not exist" if not path.exists() else "is not a directory")
        bags = [path] if (path / "metadata.yaml").is_file() else sorted(
            p.parent for p in path.rglob("metadata.yaml"))
        if not bags:
            raise BagError(path, None, "holds no rosbag2 directory (no metadata.yaml below it)")
        found += [bag for bag in bags if bag not in found]
    return found


@contextmanager
def _open_reader(path: Path) -> Iterator[Reader]:
    _check_bag_dir(path)
    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:  # rosbags, sqlite, struct, zstd ...: the storage boundary
        raise BagError(path, None, f"cannot open bag: {type(exc).__name__}: {exc}") from exc
    try:
        yield reader
    finally:
        try:
            reader.close()
        except Exception:  # closing a broken storage must not hide the original error
            _LOG.debug("error closing %s", path, exc_info=True)


def _messages(
    reader: Reader, path: Path, topics: Iterable[str]
) -> Iterator[tuple[str, str, int, bytes]]:
    """(topic, msgtype, log time, raw CDR) of ``topics``; checks counts against metadata.yaml."""
    wanted = set(topics)
    connections = [c for c in reader.connections if c.topic in wanted]
    declared = Counter[str]()
    for connection in connections:
        declared[connection.topic] += connection.msgcount
    read = Counter[str]()
    if connections:
        stream = reader.messages(connections=connections)
        while True:
            try:
                connection, log_time, raw = next(stream)
            except StopIteration:
                break
            except Exception as exc:  # the storage boundary, as in _open_reader
                raise BagError(
                    path,
                    None,
                    f"storage unreadable after {sum(read.values())} messages "
                    f"(truncated or corrupt?): {type(exc).__name__}: {exc}",
                ) from exc
            read[connection.topic] += 1
            yield connection.topic, connection.msgtype, log_time, raw
    for topic in sorted(declared):
        if read[topic] != declared[topic]:
            raise BagError(
                path,
                topic,
                f"metadata.yaml declares {declared[topic]} messages, the storage holds "
                f"{read[topic]} (truncated or corrupt storage file?)",
            )


def read_custom_data(path: str | Path) -> dict[str, str]:
    """The ``custom_data`` mapping of a bag's metadata.yaml (empty if it has none)."""
    path = Path(path)
    _check_bag_dir(path)
    try:
        document = load_yaml((path / "metadata.yaml").read_text(encoding="utf-8"))
        custom = document["rosbag2_bagfile_information"].get("custom_data") or {}
    except UnicodeDecodeError as exc:
        raise BagError(path, None, f"metadata.yaml: {not_utf8(exc)}") from None
    except (OSError, yaml.YAMLError, KeyError, TypeError, AttributeError) as exc:
        raise BagError(
            path, None, f"unreadable metadata.yaml: {type(exc).__name__}: {exc}"
        ) from None
    if not isinstance(custom, dict):
        raise BagError(path, None, f"metadata.yaml custom_data is not a mapping: {shown(custom)}")
    return {str(key): str(value) for key, value in custom.items()}


def chunk_checksums(path: str | Path) -> tuple[int, int] | None:
    """(MCAP chunks with a CRC32, MCAP chunks) over the bag's storage files; None if not MCAP."""
    path = Path(path)
    _check_bag_dir(path)
    files = sorted(path.glob("*.mcap"))
    if not files:
        return None
    counts = [0, 0]
    for file in files:
        try:
            with_crc, chunks = chunk_crcs(file)
        except (OSError, ValueError) as exc:
            raise BagError(path, None, f"{file.name}: cannot read its chunks: {exc}") from exc
        counts[0] += with_crc
        counts[1] += chunks
    return counts[0], counts[1]


def list_topics(path: str | Path) -> dict[str, TopicInfo]:
    """Every topic of the bag with its type, count and offered QoS, for creating publishers."""
    path = Path(path)
    with _open_reader(path) as reader:
        result = {}
        for name, info in sorted(reader.topics.items()):
            profiles = [q for c in info.connections for q in c.ext.offered_qos_profiles]
            result[name] = TopicInfo(
                name=name,
                msgtype=info.msgtype or "",
                message_count=info.msgcount,
                latched=any(q.durability == QosDurability.TRANSIENT_LOCAL for q in profiles),
                best_effort=any(q.reliability == QosReliability.BEST_EFFORT for q in profiles),
            )
        return result


def iter_raw_messages(
    path: str | Path, topics: Iterable[str] | None = None
) -> Iterator[RawMessage]:
    """The bag's messages (all, or those of ``topics``) in log-time order, CDR unchanged.

    The path is checked at once; storage errors surface as BagError while iterating.
    """
    path = Path(path)
    _check_bag_dir(path)
    return _iter_raw(path, None if topics is None else set(topics))


def _iter_raw(path: Path, topics: set[str] | None) -> Iterator[RawMessage]:
    with _open_reader(path) as reader:
        names = reader.topics if topics is None else topics
        for topic, msgtype, log_time, raw in _messages(reader, path, names):
            yield RawMessage(topic, msgtype, log_time, bytes(raw))


# --- read_recording ----------------------------------------------------------------------------


@dataclass
class _CameraData:
    """What was read for one camera, before it is checked and assembled."""

    name: str
    present: set[str]  # CameraTopics attributes of the topics found in the bag
    topics: CameraTopics = field(init=False)
    assembler: CameraFrameAssembler = field(init=False)
    stamps: dict[str, set[int]] = field(init=False)
    frames: list[Frame] = field(default_factory=list)
    infos: list[tuple[int, CameraIntrinsics]] = field(default_factory=list)
    frame_ids: set[str] = field(default_factory=set)

    def __post_init__(self) -> None:
        self.topics = camera_topics(self.name)
        # A bag is read whole: nothing may be dropped, unpaired stamps are reported at the end.
        self.assembler = CameraFrameAssembler(
            self.name, expect_depth="depth" in self.present, max_pending=sys.maxsize
        )
        self.stamps = {attribute: set() for attribute in _ASSEMBLER_KINDS}


def _discover_cameras(path: Path, topics: Mapping[str, str]) -> dict[str, _CameraData]:
    found: dict[str, set[str]] = defaultdict(set)
    for topic, msgtype in topics.items():
        match = _CAMERA_TOPIC.match(topic)
        if not match:
            continue
        attribute, expected = _KINDS[match["kind"]]
        if msgtype != expected:
            raise BagError(path, topic, f"type {msgtype}, expected {expected}")
        found[match["camera"]].add(attribute)
    if not found:
        raise BagError(
            path,
            None,
            "no camera topics (expected /<cam>/color/image_raw, /<cam>/color/camera_info, "
            f"/<cam>/instance_mask); topics in bag: {sorted(topics)}",
        )
    return {name: _CameraData(name, present) for name, present in sorted(found.items())}


class _Decoder:
    """Deserializes and converts messages of one bag, turning every failure into a BagError."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.typestore = jazzy_typestore()

    def message(self, topic: str, msgtype: str, raw: bytes) -> Any:
        try:
            return self.typestore.deserialize_cdr(raw, msgtype)
        except Exception as exc:  # the serde boundary: corrupt CDR
            raise BagError(self.path, topic, f"cannot deserialize {msgtype}: {exc}") from exc

    def convert(self, topic: str, msg: Any, convert: Callable[[Any], Any]) -> Any:
        try:
            return convert(msg)
        except MessageError as exc:
            stamp = stamp_to_ns(msg.header.stamp)
            raise BagError(self.path, topic, f"message at stamp {stamp}: {exc}") from exc


def read_recording(path: str | Path, *, check_ids: bool = True) -> Recording:
    """Read a bag in the DESIGN.md layout (rules in the module docstring) into a Recording.

    With ``check_ids`` every mask id must be 0 or declared in the scene (skipped when the scene
    declares no objects).
    """
    path = Path(path)
    scene = _read_scene(path)
    decoder = _Decoder(path)
    transforms = StaticTransforms()
    gripper: list[tuple[int, str, np.ndarray]] = []
    with _open_reader(path) as reader:
        topic_types = {name: info.msgtype or "" for name, info in reader.topics.items()}
        cameras = _discover_cameras(path, topic_types)
        routes = {
            getattr(camera.topics, attribute): (camera, attribute)
            for camera in cameras.values()
            for attribute in camera.present
        }
        wanted = [*routes, TF_STATIC_TOPIC, GRIPPER_POSE_TOPIC]
        for topic, msgtype, _, raw in _messages(reader, path, wanted):
            msg = decoder.message(topic, msgtype, raw)
            if topic == TF_STATIC_TOPIC:
                for transform in msg.transforms:
                    transforms.add(*decoder.convert(topic, transform, transform_from_msg))
            elif topic == GRIPPER_POSE_TOPIC:
                stamp, T = decoder.convert(topic, msg, pose_stamped_from_msg)
                gripper.append((stamp, str(msg.header.frame_id), T))
            else:
                camera, attribute = routes[topic]
                _store(decoder, camera, attribute, topic, msg)
    if TF_STATIC_TOPIC not in topic_types:
        raise BagError(path, TF_STATIC_TOPIC, "topic missing: no camera extrinsics")
    recording = Recording(
        cameras={name: _assemble(path, data, transforms) for name, data in cameras.items()},
        scene=scene,
        gripper_poses=sorted(
            (
                (stamp, _to_world(path, transforms, frame_id, GRIPPER_POSE_TOPIC) @ T)
                for stamp, frame_id, T in gripper
            ),
            key=lambda pose: pose[0],
        ),
        path=path,
    )
    if check_ids and scene.objects:
        _check_mask_ids(path, recording)
    _LOG.info(
        "read %s: cameras %s, %d frames",
        path,
        list(recording.cameras),
        sum(len(c.frames) for c in recording.cameras.values()),
    )
    return recording


def load_scene(source: str | Path) -> Scene:
    """Load a scene from a YAML file, a rosbag2 directory (its custom_data) or inline YAML text.

    A ``str`` naming an existing path is read as that path; any other ``str`` containing a newline,
    ``:`` or ``{`` (or blank) is YAML text; what remains is taken as a missing file (SceneError).
    A bag without a ``mosiv.scene`` entry gives an empty Scene (nothing declared).
    """
    if isinstance(source, str) and not Path(source).exists():
        if not source.strip() or any(mark in source for mark in "\n:{"):
            return parse_scene(source)
    path = Path(source)
    if path.is_dir():
        text = read_custom_data(path).get(SCENE_KEY)
        if text is None:
            _LOG.info("%s declares no scene (no custom_data %r)", path, SCENE_KEY)
            return Scene()
        return parse_scene(text, source=f"{path} custom_data[{SCENE_KEY}]")
    return parse_scene(read_scene_text(path), source=str(path))


def _read_scene(path: Path) -> Scene:
    text = read_custom_data(path).get(SCENE_KEY)
    if text is None:
        return Scene()
    try:
        return parse_scene(text)
    except SceneError as exc:
        raise BagError(path, None, f"scene declaration (custom_data {SCENE_KEY!r}): {exc}") from exc


def _store(decoder: _Decoder, camera: _CameraData, attribute: str, topic: str, msg: Any) -> None:
    stamp = stamp_to_ns(msg.header.stamp)
    if attribute == "camera_info":
        camera.infos.append((stamp, decoder.convert(topic, msg, camera_info_from_msg)))
        return
    kind = _ASSEMBLER_KINDS[attribute]
    allowed = CAMERA_IMAGE_ENCODINGS[kind]
    if msg.encoding not in allowed:
        raise BagError(
            decoder.path, topic, f"encoding {msg.encoding!r} at stamp {stamp}, expected {allowed}"
        )
    if stamp in camera.stamps[attribute]:
        raise BagError(decoder.path, topic, f"two messages with stamp {stamp}")
    camera.stamps[attribute].add(stamp)
    image = decoder.convert(topic, msg, partial(camera_image_from_msg, kind))
    if attribute == "color":
        camera.frame_ids.add(str(msg.header.frame_id))
    try:
        frame = camera.assembler.add(kind, stamp, image)
    except MessageError as exc:
        raise BagError(decoder.path, topic, str(exc)) from exc
    if frame is not None:
        camera.frames.append(frame)


def _unpaired(path: Path, topic: str, stamps: set[int], what: str) -> BagError:
    listed = ", ".join(str(s) for s in sorted(stamps)[:5]) + (" ..." if len(stamps) > 5 else "")
    return BagError(
        path,
        topic,
        f"{len(stamps)} stamp(s) {what} (image, mask and depth of a camera pair by exact "
        f"header stamp): {listed}",
    )


def _assemble(path: Path, data: _CameraData, transforms: StaticTransforms) -> Camera:
    topics, name = data.topics, data.name
    color = data.stamps["color"]
    if not color:
        raise BagError(path, topics.color, f"no colour images for camera {name!r}")
    if not data.infos:
        raise BagError(path, topics.camera_info, f"no CameraInfo for camera {name!r}")
    for attribute in ("mask", "depth") if "depth" in data.present else ("mask",):
        stamps, topic = data.stamps[attribute], getattr(topics, attribute)
        if missing := color - stamps:
            raise _unpaired(path, topic, missing, f"of {topics.color} have no {attribute}")
        if extra := stamps - color:
            raise _unpaired(path, topic, extra, f"have no image on {topics.color}")
    intrinsics = data.infos[0][1]
    for stamp, other in data.infos[1:]:
        if not _same_calibration(intrinsics, other):
            raise BagError(path, topics.camera_info, f"calibration changes at stamp {stamp}")
    camera_frames = sorted(data.frames, key=lambda frame: frame.stamp_ns)
    height, width = camera_frames[0].size
    if (intrinsics.height, intrinsics.width) != (height, width):
        raise BagError(
            path,
            topics.camera_info,
            f"size {intrinsics.width}x{intrinsics.height} differs from the images' "
            f"{width}x{height}",
        )
    if len(data.frame_ids) > 1:
        raise BagError(path, topics.color, f"images in several frames: {sorted(data.frame_ids)}")
    frame_id = data.frame_ids.pop() or f"{name}_optical"
    return Camera(name, intrinsics, _to_world(path, transforms, frame_id, topics.color), camera_frames)


def _same_calibration(a: CameraIntrinsics, b: CameraIntrinsics) -> bool:
    return (
        (a.width, a.height, a.distortion_model) == (b.width, b.height, b.distortion_model)
        and np.array_equal(a.K, b.K)
        and np.array_equal(a.D, b.D)
    )


def _to_world(path: Path, transforms: StaticTransforms, frame: str, asking_topic: str) -> np.ndarray:
    """T_world_frame; BagError (on /tf_static, naming ``asking_topic``) if unreachable."""
    T = transforms.to_world(frame)
    if T is None:
        raise BagError(
            path,
            TF_STATIC_TOPIC,
            f"no chain of static transforms from {WORLD_FRAME!r} to {frame!r} (needed by "
            f"{asking_topic}); frames: {transforms.frames}",
        )
    return T


def _check_mask_ids(path: Path, recording: Recording) -> None:
    declared = set(recording.scene.ids)
    for camera in recording.cameras.values():
        for frame in camera.frames:
            unknown = sorted(set(np.unique(frame.mask).tolist()) - declared - {0})
            if unknown:
                raise BagError(
                    path,
                    camera_topics(camera.name).mask,
                    f"camera {camera.name!r} stamp {frame.stamp_ns}: mask ids {unknown} are not "
                    f"declared in the scene (declared ids: {sorted(declared)})",
                )


# --- write_recording ---------------------------------------------------------------------------


def _qos(*, reliable: bool, latched: bool, depth: int) -> Qos:
    unset = QosTime(0, 0)  # 0 = the middleware default (infinite)
    return Qos(
        history=QosHistory.KEEP_LAST,
        depth=depth,
        reliability=QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
        durability=QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
        deadline=unset,
        lifespan=unset,
        liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=unset,
        avoid_ros_namespace_conventions=False,
    )


SENSOR_QOS = _qos(reliable=False, latched=False, depth=5)
"""Offered QoS of camera topics: the sensor-data profile (best effort, volatile, depth 5)."""
TF_STATIC_QOS = _qos(reliable=True, latched=True, depth=1)
"""Offered QoS of /tf_static: reliable, transient_local, depth 1 (latched)."""
POSE_QOS = _qos(reliable=True, latched=False, depth=10)
"""Offered QoS of /gripper/pose: reliable, volatile, depth 10."""


def _events(recording: Recording) -> list[tuple[int, int, str, str, Callable[[], Any]]]:
    """(stamp, order, topic, msgtype, message factory) of everything to write, unsorted."""
    types = rosbags_types()
    stamps = [f.stamp_ns for c in recording.cameras.values() for f in c.frames]
    static_stamp = min(stamps, default=0)
    tf = [
        transform_to_msg(
            types, WORLD_FRAME, f"{name}_optical", camera.T_world_optical, static_stamp
        )
        for name, camera in recording.cameras.items()
    ]
    events = [(static_stamp, -1, TF_STATIC_TOPIC, TF_MESSAGE, partial(tf_message, types, tf))]
    for stamp, T in recording.gripper_poses:
        make = partial(pose_stamped_to_msg, types, T, stamp, WORLD_FRAME)
        events.append((stamp, 0, GRIPPER_POSE_TOPIC, POSE_STAMPED, make))
    for name, camera in recording.cameras.items():
        if not camera.frames:
            raise ValueError(f"camera {name!r} has no frames")
        with_depth = [frame.depth is not None for frame in camera.frames]
        if any(with_depth) and not all(with_depth):
            raise ValueError(f"camera {name!r}: some frames have depth and some do not")
        topics, optical = camera_topics(name), f"{name}_optical"
        for frame in camera.frames:
            t = frame.stamp_ns
            mask = "mono8" if frame.mask.dtype == np.uint8 else "mono16"
            at, info = (t, optical), (types, camera.intrinsics, t, optical)
            events += [
                (t, 0, topics.camera_info, CAMERA_INFO, partial(camera_info_to_msg, *info)),
                (t, 1, topics.color, IMAGE, partial(image_to_msg, types, frame.rgb, "rgb8", *at)),
                (t, 2, topics.mask, IMAGE, partial(image_to_msg, types, frame.mask, mask, *at)),
            ]
            if frame.depth is not None:
                make = partial(image_to_msg, types, frame.depth, "32FC1", *at)
                events.append((t, 3, topics.depth, IMAGE, make))
    return events


def write_recording(
    recording: Recording, path: str | Path, *, storage: str = "mcap", compress: bool = False
) -> Path:
    """Write ``recording`` as a new bag directory in the DESIGN.md layout; return its path.

    Messages are logged at their header stamps; camera_info goes with every image (same stamp);
    ``/tf_static`` (offered latched) holds world -> ``<cam>_optical`` at the first stamp; the
    scene goes to custom_data ``mosiv.scene``. ``compress`` zstd-compresses MCAP chunks (MCAP
    only); every MCAP chunk carries its CRC32 (``io.mcap``). An existing ``path`` is never
    overwritten (BagError).
    """
    path = Path(path)
    if storage not in STORAGES:
        raise ValueError(f"storage must be one of {sorted(STORAGES)}, got {storage!r}")
    if compress and storage != "mcap":
        raise ValueError("compress is only available with storage='mcap'")
    events = sorted(_events(recording), key=lambda event: (event[0], event[1], event[2]))
    typestore = jazzy_typestore()
    qos = {TF_STATIC_TOPIC: TF_STATIC_QOS, GRIPPER_POSE_TOPIC: POSE_QOS}
    try:
        writer = Writer(path, version=9, storage_plugin=STORAGES[storage])
        if compress:
            writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        writer.open()
    except (WriterError, OSError) as exc:
        raise BagError(path, None, f"cannot create bag: {exc}") from exc
    try:
        writer.set_custom_data(SCENE_KEY, scene_to_yaml(recording.scene))
        connections = {}
        for _, _, topic, msgtype, _ in events:
            if topic not in connections:
                connections[topic] = writer.add_connection(
                    topic,
                    msgtype,
                    typestore=typestore,
                    offered_qos_profiles=[qos.get(topic, SENSOR_QOS)],
                )
        for stamp, _, topic, msgtype, make in events:
            writer.write(connections[topic], stamp, typestore.serialize_cdr(make(), msgtype))
        writer.close()
        for file in path.glob("*.mcap"):  # rosbags writes none: a flipped bit would read as data
            add_chunk_crcs(file)
    except BaseException:
        writer.abort()
        shutil.rmtree(path, ignore_errors=True)  # ours: Writer refuses existing paths
        raise
    _LOG.info("wrote %s (%s, %d messages)", path, storage, len(events))
    return path
