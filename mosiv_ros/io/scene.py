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
        family: elastic             # optional: one of FAMILIES; omitted (or null) = not
                                    # declared: identification chooses among its candidate
                                    # families by held-out error (mosiv_ros.identify.family)
        params: {E: 2.0e5}          # optional: known or initial parameters, SI units, numbers
                                    # (2.0e5 and 1e5 are numbers here, unlike in plain PyYAML);
                                    # without a family, they limit the candidate families to
                                    # those that use every one of them
    gripper:                        # optional: collider moved along /gripper/pose
      shape: sphere                 # sphere (radius) | box (half_extents) | capsule (radius,
      radius: 0.02                  #   half_length along local z); metres, > 0
      friction: 0.5                 # optional: Coulomb coefficient 0..5 (default: the simulator's)
    ground:                         # optional: the floor plane normal . x = height
      height: 0.0                   # optional: m (0 to the simulator; reconstruction removes
                                    #   the floor only where it is declared)
      normal: [0.0, 0.0, 1.0]       # optional: a tilted floor (any non-zero vector; default +z)
      friction: 0.5                 # optional: Coulomb coefficient, >= 0 (undeclared: fitted)
    effects:                        # optional: effects known to act on the scene
      - name: drag                  # non-empty string, unique; the simulator's effect names
                                    # (gravity, wind, drag, linear_drag, damping) or
                                    # camera_time_offset, mask_noise
        params: {coefficient: 0.5}  # optional: known or initial values, SI units; each a number,
                                    # a list of numbers, or a mapping from an object (or camera)
                                    # name to a number

An effect or ground property that is not declared is unknown to the consumer, not absent from
the data (DESIGN.md: an undeclared effect appears nowhere in the bag); a key given as null is not
declared. Unknown keys inside an object, an effect, the ground or the gripper are errors (a
misspelt ``params`` must not vanish silently); unknown top-level keys are kept in ``Scene.extra``
for later schema versions. The ground and the gripper are read as the synthetic recorder's scene
files read theirs (``io.fields``; ``DeclaredGripper.read`` reads both), with the same messages.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from mosiv_ros.io.errors import SceneError, not_utf8, shown
from mosiv_ros.io.fields import Fields, check_number, check_vector, is_number

SCENE_KEY = "mosiv.scene"
SCHEMA_VERSION = 1
FAMILIES = ("elastic", "plastic", "sand", "fluid")
MAX_OBJECT_ID = 65535
_OBJECT_KEYS = ("id", "name", "family", "params")
_EFFECT_KEYS = ("name", "params")
GRIPPER_SIZES = {"sphere": ("radius",), "box": ("half_extents",), "capsule": ("radius", "half_length")}
"""The simulator's collider shapes and the keys of their sizes, in ``sim.Collider``'s order."""
UP = (0.0, 0.0, 1.0)
"""The normal of a ground that declares none."""


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


MAX_YAML_NODES = 100_000
"""The most nodes (scalars, lists, mappings) a YAML text the pipeline reads may expand to, an
alias counted again at every use: far above any scene declaration, scene file, params file or
what-if request, far below an alias bomb (a few hundred characters expanding to billions)."""


def load_yaml(text: str) -> Any:
    """Python data of YAML ``text`` (safe), reading ``2.0e5`` and ``1e-3`` as numbers.

    Raises ``yaml.YAMLError`` on invalid YAML, and on YAML whose aliases expand it beyond
    ``MAX_YAML_NODES`` nodes or that nests deeper than Python's recursion limit.
    """
    loader = _Loader(text)  # a SafeLoader subclass
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        size = _expanded_size(node, {})
        if size > MAX_YAML_NODES:
            raise yaml.YAMLError(f"its aliases expand it to more than {MAX_YAML_NODES} nodes "
                                 f"({'without end' if math.isinf(size) else f'{size:.3g}'}): refused")
        return loader.construct_document(node)
    except RecursionError:
        raise yaml.YAMLError("nested too deeply to read") from None
    finally:
        loader.dispose()


def _expanded_size(node: yaml.Node, sizes: dict[int, float]) -> float:
    """Nodes under ``node`` with every alias expanded (inf for a node that contains itself)."""
    key = id(node)
    if key not in sizes:
        sizes[key] = math.inf  # reached again while being counted: it contains itself
        if isinstance(node, yaml.MappingNode):
            children = [child for pair in node.value for child in pair]
        elif isinstance(node, yaml.SequenceNode):
            children = node.value
        else:
            children = []
        sizes[key] = 1 + sum(_expanded_size(child, sizes) for child in children)
    return sizes[key]


def _plain(value: float) -> float | int:
    """A plain Python number, so that the declaration always dumps as safe YAML."""
    return int(value) if isinstance(value, int) else float(value)


RESERVED_NAME = "scene"
"""No object takes this name: estimates and reports use it for the ground's and effects' values."""


@dataclass
class SceneObject:
    """One declared object: its mask id, unique name, material family and known parameters.

    ``family`` None: the declaration leaves the family open (identification chooses it).
    """

    id: int
    name: str
    family: str | None = None
    params: dict[str, float] = field(default_factory=dict)

    def check(self, where: str = "") -> None:
        """Raise SceneError naming ``where.<field>`` if a field is invalid; normalise params."""
        prefix = f"{where}." if where else ""
        if not isinstance(self.id, int) or isinstance(self.id, bool):
            raise SceneError(f"{prefix}id", f"expected an integer, got {shown(self.id)}")
        if not 1 <= self.id <= MAX_OBJECT_ID:
            raise SceneError(f"{prefix}id", f"{self.id} is outside 1..{MAX_OBJECT_ID}")
        if not isinstance(self.name, str) or not self.name.strip():
            raise SceneError(f"{prefix}name", f"expected a non-empty string, got {shown(self.name)}")
        if self.name == RESERVED_NAME:
            raise SceneError(f"{prefix}name", f"{RESERVED_NAME!r} is reserved: it names the scene's "
                             "own status on /mosiv/material_estimates (mosiv/scene)")
        if self.family is not None and self.family not in FAMILIES:
            raise SceneError(
                f"{prefix}family",
                f"unknown material family {shown(self.family)} (expected one of {', '.join(FAMILIES)})",
            )
        if not isinstance(self.params, dict):
            raise SceneError(f"{prefix}params", f"expected a mapping, got {shown(self.params)}")
        for key, value in self.params.items():
            if not isinstance(key, str) or not is_number(value) or not math.isfinite(value):
                raise SceneError(
                    f"{prefix}params.{key}", f"expected a finite number in SI units, got {shown(value)}"
                )
        if self.params:
            _check_material_params(self.name, self.params, f"{prefix}params")
        self.params = {k: _plain(v) for k, v in self.params.items()}


def _check_material_params(name: str, params: dict[str, float], where: str) -> None:
    """SceneError naming the object and the parameter that the simulator would refuse.

    Known names and valid ranges are the simulator's own (``sim.materials.MATERIAL_PARAMS``),
    checked here so that a declaration is refused when it is read, not after reconstruction.
    """
    from mosiv_ros.sim.materials import FRICTION_ANGLE_DEG, MATERIAL_PARAMS, in_sim_units  # Warp

    specs = {spec.name: spec for spec in MATERIAL_PARAMS}
    for key, value in params.items():
        ((sim_name, sim_value),) = in_sim_units({key: value}).items()
        spec = specs.get(sim_name)
        if spec is None:
            raise SceneError(f"{where}.{key}", f"object {shown(name)}: unknown parameter {shown(key)} "
                             f"(known: {', '.join(specs)}, {FRICTION_ANGLE_DEG})")
        if not spec.in_range(sim_value):
            given = f" (given as {key} = {value:g})" if key != sim_name else ""
            raise SceneError(f"{where}.{key}", f"{spec.out_of_range(sim_value, f'object {shown(name)}')}{given}")


ParamValue = float | list[float] | dict[str, float]
"""A declared effect parameter: a number, a vector, or a number per object (or camera) name."""


@dataclass
class DeclaredEffect:
    """One declared effect: its name and known (or initial) parameter values, SI units."""

    name: str
    params: dict[str, ParamValue] = field(default_factory=dict)

    def check(self, where: str = "") -> None:
        """Raise SceneError naming ``where.<field>`` if a field is invalid; normalise params."""
        prefix = f"{where}." if where else ""
        if not isinstance(self.name, str) or not self.name.strip():
            raise SceneError(f"{prefix}name", f"expected a non-empty string, got {shown(self.name)}")
        if not isinstance(self.params, dict):
            raise SceneError(f"{prefix}params", f"expected a mapping, got {shown(self.params)}")
        self.params = {
            key: _effect_value(value, f"{prefix}params.{key}") for key, value in self.params.items()
        }


def _finite(value: object, where: str) -> float | int:
    if not is_number(value) or not math.isfinite(value):
        raise SceneError(where, f"expected a finite number in SI units, got {shown(value)}")
    return _plain(value)


def _effect_value(value: object, where: str) -> ParamValue:
    if isinstance(value, list) and value:
        return [_finite(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, dict) and value:
        for name in value:
            if not isinstance(name, str) or not name:
                raise SceneError(where, f"expected object or camera names as keys, got {shown(name)}")
        return {name: _finite(v, f"{where}.{name}") for name, v in value.items()}
    return _finite(value, where)


@dataclass
class DeclaredGround:
    """The declared floor plane normal . x = height; a field None is not declared.

    Consumers take an undeclared height as 0 (``plane``) and an undeclared normal as ``UP``; an
    undeclared friction is the simulator's default to start from, and is fitted.
    """

    height: float | None = None
    normal: tuple[float, float, float] | None = None
    friction: float | None = None

    def __post_init__(self) -> None:
        if self.height is not None:
            self.height = check_number(self.height, "ground.height")
        if self.normal is not None:
            self.normal = tuple(check_vector(self.normal, "ground.normal", 3).tolist())
            if not any(self.normal):
                raise SceneError("ground.normal", "must not be the zero vector")
        if self.friction is not None:
            self.friction = check_number(self.friction, "ground.friction", lower=0.0)

    @classmethod
    def read(cls, f: Fields) -> DeclaredGround:
        """The ground of the mapping ``f``; SceneError naming the field at fault."""
        given = {key: f.raw[key] for key in ("height", "normal", "friction") if f.has(key)}
        f.done()
        return cls(**given)

    def plane(self) -> tuple[float, tuple[float, float, float]]:
        """(height, normal) of the plane, an undeclared height 0 and normal ``UP``."""
        return (0.0 if self.height is None else self.height), (UP if self.normal is None else self.normal)

    def as_yaml(self) -> dict[str, Any]:
        """The declared fields, as the declaration's YAML has them."""
        return {key: list(value) if key == "normal" else value
                for key, value in (("height", self.height), ("normal", self.normal),
                                   ("friction", self.friction)) if value is not None}


@dataclass
class DeclaredGripper:
    """A kinematic collider moved along /gripper/pose: shape, size as ``sim.Collider`` takes it.

    ``friction`` None: not declared (the simulator's default).
    """

    shape: str
    size: tuple[float, ...]
    friction: float | None = None

    @classmethod
    def read(cls, f: Fields) -> DeclaredGripper:
        """The shape, size and friction keys of the mapping ``f`` (other keys are the caller's)."""
        shape = f.string("shape", choices=tuple(GRIPPER_SIZES))
        if shape == "box":
            size = tuple(f.vector("half_extents", 3, positive=True).tolist())
        else:
            size = tuple(f.number(key, positive=True) for key in GRIPPER_SIZES[shape])
        friction = f.number("friction", lower=0.0, upper=5.0) if f.has("friction") else None
        return cls(shape, size, friction)

    def as_yaml(self) -> dict[str, Any]:
        """The gripper as the declaration's YAML has it."""
        values = [list(self.size)] if self.shape == "box" else list(self.size)
        friction = {} if self.friction is None else {"friction": self.friction}
        return {"shape": self.shape, **dict(zip(GRIPPER_SIZES[self.shape], values, strict=True)), **friction}


def _read_gripper(raw: object) -> DeclaredGripper:
    f = Fields(raw, "gripper")
    gripper = DeclaredGripper.read(f)
    f.done(f" for a {gripper.shape}")
    return gripper


@dataclass
class Scene:
    """A validated scene declaration (schema v1, see the module docstring).

    Constructing one validates it; an empty scene (no objects) means "nothing declared". A ground
    or gripper given as a mapping is read as the declaration's YAML.
    """

    objects: list[SceneObject] = field(default_factory=list)
    gripper: DeclaredGripper | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    ground: DeclaredGround | None = None
    effects: list[DeclaredEffect] = field(default_factory=list)

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
                    f"{where}.name", f"name {shown(obj.name)} already used by objects[{names[obj.name]}]"
                )
            ids[obj.id] = index
            names[obj.name] = index
        if self.gripper is not None and not isinstance(self.gripper, DeclaredGripper):
            self.gripper = _read_gripper(self.gripper)
        if self.ground is not None and not isinstance(self.ground, DeclaredGround):
            self.ground = DeclaredGround.read(Fields(self.ground, "ground"))
        effect_names: dict[str, int] = {}
        for index, effect in enumerate(self.effects):
            effect.check(f"effects[{index}]")
            if effect.name in effect_names:
                raise SceneError(
                    f"effects[{index}].name",
                    f"name {shown(effect.name)} already used by effects[{effect_names[effect.name]}]",
                )
            effect_names[effect.name] = index
        reserved = {"version", "objects", "gripper", "ground", "effects"} & set(self.extra)
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
        document = load_yaml(yaml_text)
    except yaml.YAMLError as exc:
        raise SceneError("", f"invalid YAML: {exc}", source) from None
    if document is None:
        return Scene()
    if not isinstance(document, dict):
        raise SceneError("", f"expected a mapping at top level, got {shown(document)}", source)
    document = dict(document)
    try:
        version = document.pop("version", SCHEMA_VERSION)
        if version != SCHEMA_VERSION:
            raise SceneError("version", f"unsupported schema version {shown(version)} (expected 1)")
        raw_objects = document.pop("objects", None) or []
        if not isinstance(raw_objects, list):
            raise SceneError("objects", f"expected a list, got {shown(raw_objects)}")
        objects = [_object_from_yaml(raw, f"objects[{i}]") for i, raw in enumerate(raw_objects)]
        raw_effects = document.pop("effects", None) or []
        if not isinstance(raw_effects, list):
            raise SceneError("effects", f"expected a list, got {shown(raw_effects)}")
        effects = [_effect_from_yaml(raw, f"effects[{i}]") for i, raw in enumerate(raw_effects)]
        return Scene(
            objects=objects,
            gripper=document.pop("gripper", None),
            ground=document.pop("ground", None),
            effects=effects,
            extra=document,
        )
    except SceneError as exc:
        raise SceneError(exc.field, exc.problem, source) from None


def _object_from_yaml(raw: object, where: str) -> SceneObject:
    if not isinstance(raw, dict):
        raise SceneError(where, f"expected a mapping, got {shown(raw)}")
    unknown = sorted(set(raw) - set(_OBJECT_KEYS), key=str)
    if unknown:
        raise SceneError(
            f"{where}.{unknown[0]}", f"unknown key (allowed: {', '.join(_OBJECT_KEYS)})"
        )
    for key in ("id", "name"):
        if key not in raw:
            raise SceneError(f"{where}.{key}", "missing")
    params = raw.get("params")
    return SceneObject(raw["id"], raw["name"], raw.get("family"), {} if params is None else params)


def _effect_from_yaml(raw: object, where: str) -> DeclaredEffect:
    if not isinstance(raw, dict):
        raise SceneError(where, f"expected a mapping, got {shown(raw)}")
    unknown = sorted(set(raw) - set(_EFFECT_KEYS), key=str)
    if unknown:
        raise SceneError(
            f"{where}.{unknown[0]}", f"unknown key (allowed: {', '.join(_EFFECT_KEYS)})"
        )
    if "name" not in raw:
        raise SceneError(f"{where}.name", "missing")
    params = raw.get("params")
    return DeclaredEffect(raw["name"], {} if params is None else params)


def scene_to_yaml(scene: Scene) -> str:
    """YAML text of ``scene`` that ``parse_scene`` reads back to an equal Scene."""
    document: dict[str, Any] = {"version": SCHEMA_VERSION, "objects": []}
    for obj in scene.objects:
        entry: dict[str, Any] = {"id": obj.id, "name": obj.name}
        if obj.family is not None:
            entry["family"] = obj.family
        if obj.params:
            entry["params"] = dict(obj.params)
        document["objects"].append(entry)
    if scene.gripper is not None:
        document["gripper"] = scene.gripper.as_yaml()
    if scene.ground is not None:
        document["ground"] = scene.ground.as_yaml()
    if scene.effects:
        document["effects"] = [
            {"name": e.name, **({"params": dict(e.params)} if e.params else {})}
            for e in scene.effects
        ]
    document.update(scene.extra)
    return yaml.safe_dump(document, sort_keys=False)


def read_scene_text(path: Path) -> str:
    """The text of a scene file; SceneError naming it if it cannot be read or is not UTF-8."""
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise SceneError("", not_utf8(exc), str(path)) from None
    except OSError as exc:
        raise SceneError("", f"cannot read scene file: {exc.strerror}", str(path)) from None
