"""One configuration dataclass per stage, shared by the command line, the ROS nodes and the tests.

Each field is a node parameter of the same name, or a group of them (a dataclass of its own,
``_group``): a group's name is their ROS namespace, ``search.samples`` the parameter ``samples``
of the group ``search``, nested in a params file as ``search: {samples: 32}``. A field's
default is the parameter's default (also written in ``config/mosiv.yaml``), its ``help``
metadata is the parameter's description, its ``range`` metadata, where it has one, the closed
interval a number (or each number of a list) must lie in (the nodes declare it as the
parameter's range and refuse other values, at start and at run time, as ``mosiv run`` refuses
them in a params file: ``check``), and ``run_time`` says whether the node takes a change while
it runs (it refuses a change of any other parameter).
Values are in SI units (seconds, metres) unless the name says otherwise.

This module only describes settings; it does not read files or talk to ROS.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import typing
from dataclasses import dataclass, field
from typing import Any

from mosiv_ros.io.scene import FAMILIES


def _param(default: Any, help: str, low: float | None = None, high: float | None = None,
           run_time: bool = False) -> Any:
    """A dataclass field: the parameter's description, range [low, high] if any, ``run_time``.

    ``run_time``: the node takes a change of the parameter while it runs.
    """
    metadata = {"help": help, "run_time": run_time}
    if low is not None:
        metadata["range"] = (low, high)
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata=metadata)
    return field(default=default, metadata=metadata)


def _group(config_type: type) -> Any:
    """A dataclass field holding a group of parameters: their ROS namespace is the field's name."""
    return field(default_factory=config_type, metadata={"group": config_type})


HOLDOUT = 0.3
"""Fraction of the frames a fit leaves out to be judged on: the recording's last by ``mosiv run``,
``mosiv graph`` and ``mosiv close-loop``, the fit window's last when a family is chosen."""

SCENE_HELP = (
    "Scene declaration: a rosbag2 directory (its metadata custom_data 'mosiv.scene'), a YAML "
    "file or inline YAML text; overrides the recording's declaration. Empty: the recording's."
)


@dataclass
class ReplayConfig:
    """bag_replay_node: publish a recorded bag's topics with their recorded stamps."""

    bag: str = _param("", "Path of the rosbag2 directory to replay (required).")
    rate: float = _param(
        1.0, "Playback rate: 1.0 = real time, 2.0 = twice as fast, 0 = as fast as possible.",
        0.0, 100.0)
    topics: list[str] = _param([], "Topics to replay; empty = every topic in the bag.")
    start_delay: float = _param(
        0.5, "Seconds to wait after creating the publishers before the first message.",
        0.0, 60.0)
    wait_for_subscribers: int = _param(
        0, "Wait until every image topic has this many subscribers before starting.",
        0, 100)
    wait_timeout: float = _param(
        10.0, "Longest wait for subscribers, seconds; then replay anyway with a warning.",
        0.0, 3600.0)
    loop: bool = _param(False, "Replay the bag again from the start when it ends.")
    exit_when_done: bool = _param(True, "Shut the node down once the bag has been replayed.")
    linger: float = _param(
        2.0, "Seconds to keep serving latched topics after the last message before exiting.",
        0.0, 3600.0)


@dataclass
class TrackConfig:
    """Surface tracks of stage 1 (reconstruction_node parameters ``tracks.*``)."""

    flow_tolerance: float = _param(
        1.0, "Largest forward-backward optical flow error, pixels, of a track's step (a step that "
        "misses it ends the track).", 0.01, 100.0)
    spacing: float = _param(
        3.0, "Smallest distance, pixels, between a new track and the object's other tracks in one camera.",
        1.0, 1000.0)
    quality: float = _param(
        0.01, "A new track starts where the image's corner strength is at least this fraction of the "
        "object's strongest (Shi-Tomasi quality level).", 1.0e-4, 1.0)


@dataclass
class ReconstructionConfig:
    """reconstruction_node: group camera frames by stamp, per-object geometry per frame (stage 1)."""

    cameras: list[str] = _param([], "Camera names (topic prefixes); empty = discover /<cam>/color/image_raw topics.")
    sync_tolerance: float = _param(
        0.005, "Largest stamp difference, seconds, between frames of one frame set.",
        0.0, 1.0)
    use_depth: bool = _param(True, "Fuse /<cam>/depth/image_rect when the recording has it.")
    voxel_size: float = _param(0.005, "Edge of the reconstruction voxel grid, metres.", 5.0e-4, 0.5)
    workspace: list[float] = _param(
        [], "Box to reconstruct in, world frame, metres: [xmin, ymin, zmin, xmax, ymax, zmax]; "
        "empty = a cube around the point the cameras look at, reaching to the farthest camera.", -1000.0, 1000.0)
    min_views: int = _param(
        0, "Cameras whose image a voxel must project into to be kept; 0 = every camera of the frame set.", 0, 100)
    depth_tolerance: float = _param(
        0.0025, "Depth carving margin, metres (about half a voxel plus the depth noise): a voxel "
        "nearer than depth - margin is empty space.", 0.0, 0.5)
    mask_filter: int = _param(
        3, "Side, pixels, of the majority filter applied to instance masks (odd; 0 or 1 = off).", 0, 31)
    partial_set_timeout: float = _param(
        0.5, "Seconds after which a frame set still lacking cameras is reconstructed without them, "
        "or without the gripper's pose at its stamp: frames that much later came, or none for that long.",
        0.0, 60.0)
    image_history: int = _param(
        30, "Messages each camera topic's subscription keeps while the node is busy (keep-last depth of "
        "the sensor-data profile): a stall of fewer frames loses none; each held message costs its "
        "size (a 640x480 colour image 0.9 MB).", 1, 10000)
    tracks: TrackConfig = _group(TrackConfig)
    scene: str = _param("", SCENE_HELP)


@dataclass
class LiftingConfig:
    """lifting_node: fill each object's first observed frame with simulation particles (stage 2)."""

    particle_spacing: float = _param(
        0.01, "Spacing of the particles that fill each object, metres (the grid is twice as coarse).", 0.001, 0.5)
    boundary_band: float = _param(
        0.008, "Half-width of the band of boundary particles around the surface, metres.",
        0.0, 0.5)
    boundary_beta: float = _param(
        5.0e3, "Sharpness beta of the boundary volume sigmoid, 1/m (M-PhyGs Eq. 1).",
        1.0, 1.0e7)
    boundary_eps: float = _param(1.0e-4, "Floor epsilon of the boundary volume sigmoid (M-PhyGs Eq. 1).", 0.0, 1.0)
    density_iterations: int = _param(
        1, "Rounds of 3x3x3 mean filtering of the occupancy density (occupied cells reset to 1).", 0, 20)
    density_threshold: float = _param(0.5, "Density at and above which a cell is inside an object.", 0.0, 1.0)
    consensus_frames: int = _param(
        2, "Later observed frames each object's lifted hull is intersected with, each moved onto it "
        "(removes hull that an occluding object left in the lifted frame); 0 = lift the frame as observed.", 0, 100)
    consensus_max_removed: float = _param(
        0.05, "Largest fraction of an object's voxels one later frame may remove; a frame that would "
        "remove more (the object deformed or turned) is not used for it.", 0.0, 1.0)
    border_wait: int = _param(
        5, "Frames after the first complete one in which to look for one that no image border cuts "
        "(an object's part beyond the border is not reconstructed); the first such is lifted, else the "
        "first complete one; 0 = lift the first complete frame.", 0, 1000)
    consensus_timeout: float = _param(
        5.0, "lifting_node: seconds to wait for the later frames after the first complete one; "
        "then lift with those that came.", 0.0, 600.0)
    scene: str = _param("", SCENE_HELP)


@dataclass
class SearchConfig:
    """The gradient-free search before Adam (identify_node parameters ``search.*``)."""

    samples: int = _param(32, "Latin hypercube samples of the global search before Adam; 0 = none.", 0, 100000)
    rounds: int = _param(
        3, "Further search rounds, each sampling a 3x narrower box around the best so far; 0 = none.", 0, 100)
    starts: int = _param(
        3, "Best points of the first search round that each go through the further rounds.", 1, 100)
    frames: int = _param(0, "Frames the search simulates; 0 = the whole window.", 0, 100000)
    race: float = _param(
        0.05, "Starts whose search ends score within this fraction of the best end's loss each run the "
        "first curriculum stage, and the one with the lowest loss over that stage's last pass over its "
        "windows goes on; 0 = the best end only.", 0.0, 10.0)


@dataclass
class CurriculumConfig:
    """Adam over a horizon curriculum of windows (identify_node parameters ``curriculum.*``)."""

    horizons: list[int] = _param(
        [5, 10, 15, 25, 0], "Window length of each curriculum stage in frames; 0 = all frames.", 0, 100000)
    iterations: int = _param(20, "Optimiser iterations per curriculum stage.", 0, 100000)
    windows: int = _param(3, "Windows per curriculum stage, spread over the sequence; later ones resynced.", 1, 1000)
    learning_rate: float = _param(0.05, "Adam step size in the well-conditioned parameter coordinates.", 1.0e-6, 10.0)
    velocity_learning_rate: float = _param(0.01, "Adam step size of initial velocities, m/s and rad/s.", 0.0, 10.0)


@dataclass
class LossConfig:
    """The objective the search and Adam minimise (identify_node parameters ``loss.*``)."""

    chamfer_weight: float = _param(1.0, "Weight of the per-object Chamfer loss.", 0.0, 1.0e6)
    silhouette_weight: float = _param(0.1, "Weight of the per-object silhouette loss.", 0.0, 1.0e6)
    per_object: bool = _param(True, "Per-object losses (MOSIV); False = scene-level ablation.")
    track_weight: float = _param(
        1.0, "Weight of the per-object surface track loss (tracks attached to the particles at the first "
        "fitted frame); 0 = off. Nothing changes for a recording without tracks.", 0.0, 1.0e6)
    track_scale: float = _param(
        0.005, "Scale of the track loss's pseudo-Huber, metres: a track's error counts as its square "
        "below it, growing only linearly beyond (a drifted track's pull is bounded).", 1.0e-5, 1.0)


@dataclass
class FitConfig:
    """The fit's own parameters: identify_node's that ``identify.fit.FitSettings`` takes too."""

    search: SearchConfig = _group(SearchConfig)
    curriculum: CurriculumConfig = _group(CurriculumConfig)
    loss: LossConfig = _group(LossConfig)
    max_modulus: float = _param(
        1.0e6, "Pa: the fit keeps E and bulk moduli at or below it (WARN when one ends there). A stiffer "
        "object hardly deforms at a reconstruction's millimetres and frame rate, and its simulation takes "
        "more time steps (as the square root of the modulus).", 1.0e4, 1.0e12)
    cpu_workers: int = _param(
        0, "On the CPU: simulations the batched losses (search, uncertainty) run side by side, one per "
        "core; 0 = every core. The results do not depend on it.", 0, 1024)
    checkpoint_dir: str = _param("", "Directory for fit checkpoints; empty = no checkpoints. A rerun resumes.")


@dataclass
class IdentifyConfig(FitConfig):
    """identify_node: fit per-object material parameters with the differentiable simulator (stage 3)."""

    device: str = _param("auto", "Simulation device: 'auto' (CUDA when available), 'cpu' or 'cuda:N'.")
    window: int = _param(0, "Observed frames to fit; 0 = every frame received before the stream goes idle.", 0, 100000)
    idle_timeout: float = _param(3.0, "Seconds without a new observed frame (or surface tracks, while a node "
                                 "publishes them) after which the fit starts.", 0.0, 3600.0)
    uncertainty: bool = _param(True, "Estimate a standard deviation per parameter (Laplace).")
    density_ratios: bool = _param(
        False, "Also fit the objects' undeclared densities. Only their ratios show (in contact), so "
        "when no density is declared the lowest-id object's stays at its default and sets the scale.")
    families: list[str] = _param(
        list(FAMILIES),
        "Candidate material families of an object whose family the scene does not declare: each "
        f"is fitted on the first {(1 - HOLDOUT) * 100:g} % of the window and the one whose rollout is "
        "closest (Chamfer) to the held-out rest is chosen, then fitted on the whole window. One entry: that family, "
        "no selection.")
    output_yaml: str = _param(
        "material_estimates.yaml", "Where to write the estimates (a prediction_node params file)."
    )
    close_loop: bool = _param(
        False, "After the fit, close the loop: look for an effect the model lacks in the residual, "
        "refit with it, report before and after (mosiv close-loop) into close_loop_dir.")
    close_loop_dir: str = _param("close_loop", "Directory of the loop closure's report and closed scene.")
    scene: str = _param("", SCENE_HELP)


MAX_SPEED = 100.0
"""m/s: the largest linear speed a what-if request (``initial_velocities``) may give an object."""
MAX_SPIN = 1000.0
"""rad/s: the largest angular speed a what-if request may give an object."""


@dataclass
class PredictionConfig:
    """prediction_node: roll the identified digital twin forward and publish the predicted motion."""

    device: str = _param("auto", "Simulation device: 'auto' (CUDA when available), 'cpu' or 'cuda:N'.")
    horizon: float = _param(
        2.0, "Seconds to predict past the last observed frame. Settable at run time.", 0.0, 60.0, run_time=True)
    frame_rate: float = _param(
        10.0, "Predicted frames per second. Settable at run time.", 0.1, 1000.0, run_time=True)
    estimates: str = _param(
        "", "The material estimates (YAML text). identify_node's output_yaml file sets it: "
        "--params-file FILE. Empty: from /mosiv/material_estimates. Settable at run time.", run_time=True)
    initial_velocities: str = _param(
        "", "What-if request: new initial velocities by object, YAML {name: [vx, vy, vz]} in m/s "
        f"(six values add wx, wy, wz in rad/s; at most {MAX_SPEED:g} m/s and {MAX_SPIN:g} rad/s). With "
        "a request, the prediction is every frame from the first observed one. Empty: as identified. "
        "Settable at run time.", run_time=True)
    swapped_params: str = _param(
        "", "What-if request: material parameters replacing the identified ones, YAML {name: "
        "{parameter: value}} in SI units (a friction angle as friction_angle_deg). Empty: as "
        "identified. Settable at run time.", run_time=True)
    scene: str = _param("", SCENE_HELP)


@dataclass
class BatchConfig:
    """``mosiv batch``: where the recordings run (Ray) and what runs on each; not a node's."""

    address: str = _param(
        "", "Ray cluster to join (ray.init(address=...)), e.g. 'auto' or 'ray://head:10001'; empty = "
        "a Ray of this machine's own, started for the batch and stopped after it.")
    cpus: int = _param(0, "CPU cores of the Ray started on this machine; 0 = all of them.", 0, 100000)
    per_gpu: int = _param(
        1, "Recordings that share one GPU at a time (each asks Ray for 1/per_gpu of one): a fit of a few "
        "thousand particles leaves most of a GPU idle; a full-size suite scene's peaks at about 9 GB.", 1, 64)
    close_loop: bool = _param(False, "Also close the loop on each recording (mosiv close-loop).")


STAGE_CONFIGS: dict[str, type] = {
    "bag_replay_node": ReplayConfig,
    "reconstruction_node": ReconstructionConfig,
    "lifting_node": LiftingConfig,
    "identify_node": IdentifyConfig,
    "prediction_node": PredictionConfig,
}
"""Every node of the package (its executable's name) and its parameters: setup.py installs these."""

REPLAY_NODE = "bag_replay_node"
"""The node that replays a recording into the pipeline."""
PIPELINE_NODES: tuple[str, ...] = tuple(node for node in STAGE_CONFIGS if node != REPLAY_NODE)
"""The stage nodes in pipeline order (each before the one it feeds): every node but the replay."""


def parameters(config_type: type, prefix: str = "") -> list[tuple[str, dataclasses.Field, Any]]:
    """(name, field, type) of every parameter of a stage config, in order.

    A group's parameters are named with the group's name and a dot (``search.samples``): the
    nesting is the ROS parameter namespace, and a params file may nest them as mappings.
    """
    hints = typing.get_type_hints(config_type)
    found = []
    for f in dataclasses.fields(config_type):
        group = f.metadata.get("group")
        if group is not None:
            found += parameters(group, f"{prefix}{f.name}.")
        else:
            found.append((prefix + f.name, f, hints[f.name]))
    return found


def value_of(config: Any, name: str) -> Any:
    """The value of the parameter ``name`` (dotted within groups) of a stage config."""
    return functools.reduce(getattr, name.split("."), config)


def describe(config_type: type) -> list[tuple[str, Any, str]]:
    """(name, default, description) of every parameter of a stage config."""
    defaults = config_type()
    return [(name, value_of(defaults, name), f.metadata.get("help", ""))
            for name, f, _ in parameters(config_type)]


def value_range(config_type: type, name: str) -> tuple[float, float] | None:
    """The closed interval [low, high] a parameter's numbers must lie in, or None."""
    return next(f.metadata.get("range") for known, f, _ in parameters(config_type) if known == name)


def check(config: Any) -> Any:
    """Return a stage config whose numbers all lie in their ranges; else ValueError naming one."""
    for name, f, _ in parameters(type(config)):
        bounds = f.metadata.get("range")
        value = value_of(config, name)
        if bounds is None:
            continue
        for number in value if isinstance(value, list) else [value]:
            if isinstance(number, bool) or not isinstance(number, int | float):
                raise ValueError(f"{name}: expected a number, got {number!r}")
            if not bounds[0] <= number <= bounds[1]:  # NaN is outside too
                raise ValueError(f"{name}: {number!r} is out of range [{bounds[0]:g}, {bounds[1]:g}]")
    return config


def flat(values: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Values by parameter name from a mapping that may nest groups, as a ROS params file does.

    {"search": {"samples": 8}} gives {"search.samples": 8}.
    """
    found = {}
    for key, value in values.items():
        if isinstance(value, dict):
            found |= flat(value, f"{prefix}{key}.")
        else:
            found[prefix + key] = value
    return found


def build(config_type: type, values: dict[str, Any]) -> Any:
    """A stage config with ``values`` by parameter name, the defaults elsewhere; not checked."""
    given = {}
    for f in dataclasses.fields(config_type):
        group = f.metadata.get("group")
        if group is not None:
            given[f.name] = build(group, {name.removeprefix(f"{f.name}."): value for name, value in values.items()
                                          if name.startswith(f"{f.name}.")})
        elif f.name in values:
            given[f.name] = values[f.name]
    return config_type(**given)


def from_mapping(config_type: type, values: dict[str, Any]) -> Any:
    """Build a stage config from a mapping, rejecting unknown keys with their names.

    Groups may nest (``{"search": {"samples": 8}}``) or be dotted (``{"search.samples": 8}``).
    Values outside their ranges are refused (``check``).
    """
    values = flat(values)
    names = [name for name, _, _ in parameters(config_type)]
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise ValueError(
            f"{config_type.__name__}: unknown parameter(s) {', '.join(unknown)}; "
            f"known: {', '.join(sorted(names))}"
        )
    return check(build(config_type, values))


def updated(config: Any, values: dict[str, Any]) -> Any:
    """A copy of a stage config with ``values`` by parameter name (groups nested or dotted), checked."""
    current = {name: value_of(config, name) for name, _, _ in parameters(type(config))}
    return from_mapping(type(config), copy.deepcopy(current) | flat(values))
