"""Scene declarations: which objects a recording shows and what is known about them.

A scene declaration travels as YAML text in a bag's ``metadata.yaml`` ``custom_data`` under the
key ``mosiv.scene`` (see DESIGN.md), or as a YAML file / node parameter that overrides it. This
module parses, validates and writes it. It is not for ground truth (``ground_truth.yaml`` sidecar,
read only by evaluation code) and holds no physics.

Schema, version 1::

    version: 1                      # optional; only 1 is understood
    objects:                        # optional; empty or absent = nothing declared
      - id: 1                       # int 1..65535, unique; the value in instance masks
        name: red_ball              # non-empty string, unique
        family: elastic             # one of FAMILIES
        params: {E: 2.0e5}          # optional: known or initial parameters, SI units, numbers
                                    # (2.0e5 and 1e5 are numbers here, unlike in plain PyYAML)
    gripper:                        # optional: collider moved along /gripper/pose
      shape: sphere                 # non-empty string; 'sphere' requires radius
      radius: 0.02                  # metres, > 0

Unknown keys inside an object are errors (a misspelt ``params`` must not vanish silently);
unknown top-level keys are kept in ``Scene.extra`` for later schema versions. Gripper keys other
than ``shape`` (and ``radius`` for spheres) are passed through unchecked: the simulator that uses
the collider checks them.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from mosiv_ros.io.errors import SceneError

_LOG = logging.getLogger(__name__)

SCENE_KEY = "mosiv.scene"
SCHEMA_VERSION = 1
FAMILIES = ("elastic", "plastic", "sand", "fluid")
MAX_OBJECT_ID = 65535
_OBJECT_KEYS = ("id", "name", "family", "params")


class _Loader(yaml.SafeLoader):
    """PyYAML's safe loader, also reading ``2.0e5`` and ``1e-3`` as floats (as YAML 1.2 does).

    PyYAML follows YAML 1.1, where an exponent needs a dot and a sign, so ``E: 2.0e5`` would be
    the string '2.0e5'.
    """


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


@dataclass
class SceneObject:
    """One declared object: its mask id, unique name, material family and known parameters."""

    id: int
    name: str
    family: str
    params: dict[str, float] = field(default_factory=dict)

    def check(self, where: str = "") -> None:
        """Raise SceneError naming ``where.<field>`` if a field is invalid; normalise params."""
        prefix = f"{where}." if where else ""
        if not isinstance(self.id, int) or isinstance(self.id, bool):
            raise SceneError(f"{prefix}id", f"expected an integer, got {self.id!r}")
        if not 1 <= self.id <= MAX_OBJECT_ID:
            raise SceneError(f"{prefix}id", f"{self.id} is outside 1..{MAX_OBJECT_ID}")
        if not isinstance(self.name, str) or not self.name.strip():
            raise SceneError(f"{prefix}name", f"expected a non-empty string, got {self.name!r}")
        if self.family not in FAMILIES:
            raise SceneError(
                f"{prefix}family",
                f"unknown material family {self.family!r} (expected one of {', '.join(FAMILIES)})",
            )
        if not isinstance(self.params, dict):
            raise SceneError(f"{prefix}params", f"expected a mapping, got {self.params!r}")
        for key, value in self.params.items():
            if not isinstance(key, str) or not _is_number(value) or not math.isfinite(value):
                raise SceneError(
                    f"{prefix}params.{key}", f"expected a finite number in SI units, got {value!r}"
                )
        # Plain Python numbers only, so that the declaration always dumps as safe YAML.
        self.params = {
            k: int(v) if isinstance(v, int) else float(v) for k, v in self.params.items()
        }


def _check_gripper(gripper: object) -> None:
    if not isinstance(gripper, dict):
        raise SceneError("gripper", f"expected a mapping, got {gripper!r}")
    shape = gripper.get("shape")
    if not isinstance(shape, str) or not shape:
        raise SceneError("gripper.shape", f"expected a non-empty string, got {shape!r}")
    if shape == "sphere":
        radius = gripper.get("radius")
        if not _is_number(radius) or not radius > 0:
            raise SceneError("gripper.radius", f"expected a positive number (m), got {radius!r}")


@dataclass
class Scene:
    """A validated scene declaration (schema v1, see the module docstring).

    Constructing one validates it; an empty scene (no objects) means "nothing declared".
    """

    objects: list[SceneObject] = field(default_factory=list)
    gripper: dict[str, Any] | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        ids: dict[int, int] = {}
        names: dict[str, int] = {}
        for index, obj in enumerate(self.objects):
            where = f"objects[{index}]"
            obj.check(where)
            if obj.id in ids:
                raise SceneError(
                    f"{where}.id", f"id {obj.id} already used by objects[{ids[obj.id]}]"
                )
            if obj.name in names:
                raise SceneError(
                    f"{where}.name", f"name {obj.name!r} already used by objects[{names[obj.name]}]"
                )
            ids[obj.id] = index
            names[obj.name] = index
        if self.gripper is not None:
            _check_gripper(self.gripper)
        reserved = {"version", "objects", "gripper"} & set(self.extra)
        if reserved:
            raise SceneError("extra", f"keys {sorted(reserved)} are schema fields, not extras")

    @property
    def ids(self) -> list[int]:
        """The declared object ids, in declaration order."""
        return [obj.id for obj in self.objects]

    def object_by_id(self, object_id: int) -> SceneObject:
        """The object declared with ``object_id``; SceneError if there is none."""
        for obj in self.objects:
            if obj.id == object_id:
                return obj
        raise SceneError("objects", f"no object with id {object_id} (declared ids: {self.ids})")


def parse_scene(yaml_text: str, source: str = "<string>") -> Scene:
    """Parse and validate a scene declaration; SceneError names ``source`` and the field."""
    try:
        document = yaml.load(yaml_text, Loader=_Loader)  # a SafeLoader subclass
    except yaml.YAMLError as exc:
        raise SceneError("", f"invalid YAML: {exc}", source) from None
    if document is None:
        return Scene()
    if not isinstance(document, dict):
        raise SceneError("", f"expected a mapping at top level, got {document!r}", source)
    document = dict(document)
    try:
        version = document.pop("version", SCHEMA_VERSION)
        if version != SCHEMA_VERSION:
            raise SceneError("version", f"unsupported schema version {version!r} (expected 1)")
        raw_objects = document.pop("objects", None) or []
        if not isinstance(raw_objects, list):
            raise SceneError("objects", f"expected a list, got {raw_objects!r}")
        objects = [_object_from_yaml(raw, f"objects[{i}]") for i, raw in enumerate(raw_objects)]
        return Scene(objects=objects, gripper=document.pop("gripper", None), extra=document)
    except SceneError as exc:
        raise SceneError(exc.field, exc.problem, source) from None


def _object_from_yaml(raw: object, where: str) -> SceneObject:
    if not isinstance(raw, dict):
        raise SceneError(where, f"expected a mapping, got {raw!r}")
    unknown = sorted(set(raw) - set(_OBJECT_KEYS), key=str)
    if unknown:
        raise SceneError(
            f"{where}.{unknown[0]}", f"unknown key (allowed: {', '.join(_OBJECT_KEYS)})"
        )
    for key in ("id", "name", "family"):
        if key not in raw:
            raise SceneError(f"{where}.{key}", "missing")
    params = raw.get("params")
    return SceneObject(raw["id"], raw["name"], raw["family"], {} if params is None else params)


def scene_to_yaml(scene: Scene) -> str:
    """YAML text of ``scene`` that ``parse_scene`` reads back to an equal Scene."""
    document: dict[str, Any] = {"version": SCHEMA_VERSION, "objects": []}
    for obj in scene.objects:
        entry: dict[str, Any] = {"id": obj.id, "name": obj.name, "family": obj.family}
        if obj.params:
            entry["params"] = dict(obj.params)
        document["objects"].append(entry)
    if scene.gripper is not None:
        document["gripper"] = dict(scene.gripper)
    document.update(scene.extra)
    return yaml.safe_dump(document, sort_keys=False)


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
        # Imported here: bag.py builds on this module, this one only borrows its metadata reader.
        from mosiv_ros.io.bag import read_custom_data

        text = read_custom_data(path).get(SCENE_KEY)
        if text is None:
            _LOG.info("%s declares no scene (no custom_data %r)", path, SCENE_KEY)
            return Scene()
        return parse_scene(text, source=f"{path} custom_data[{SCENE_KEY}]")
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise SceneError("", f"cannot read scene file: {exc.strerror}", str(path)) from None
    return parse_scene(text, source=str(path))
