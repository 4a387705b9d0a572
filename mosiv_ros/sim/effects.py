"""Effects: physical terms with their own parameters, plugged into every simulation substep.

The extension point. An ``Effect`` subclass declares its parameters (``ParamSpec``; stored in the
simulator's ``Parameters`` as ``<effect name>.<param>`` and fitted with the same gradients as
the material parameters) and either names a uniform acceleration or implements one or both hooks:

- ``uniform``: the name of the effect's vector parameter (3 components per batch) when the effect
  is an acceleration the same everywhere (gravity, a steady wind). The grid passes add the sum
  of these to every node's velocity (``v = p / m + dt (a + g)``), so such an effect launches no
  kernel of its own.

- ``accelerate(grid, values)``: runs after particle-to-grid, before the grid update. It adds
  accelerations (m/s^2) to ``grid.a``, one vec3 per (batch, object, node), from the grid mass and
  momentum (read-only), at nodes with mass. The grid update then integrates ``v = p / m + dt a``.
  Every node with mass lies in the box of nodes the grid passes run over (``GridView``): a hook
  may launch one thread per node of it rather than of the whole grid.
- ``stress(particles, values)``: runs before particle-to-grid. It adds a Kirchhoff stress (Pa) to
  ``particles.tau``, one mat33 per particle, from the particle state (read-only); P2G scatters
  it with the material stress.

Both hooks must only *add*, with ``wp.atomic_add``: an in-place ``a[i] = a[i] + ...`` would
give wrong adjoints on the tape. ``values`` maps the effect's own parameter names to their
replicated arrays: read value ``j`` (layout ``[batch][object][component]``) in thread ``tid``
with ``mosiv_ros.sim.params.param(values, j, tid)``. Built-in effects: gravity, a uniform body
force (wind), linear and quadratic air drag, Kelvin-Voigt damping, and a spatially periodic
force field (a position-dependent force, for testing what no uniform effect explains), and a
smooth polynomial force field (what the loop closure fits when no named effect explains a
force). Ground
friction and a
tilted floor are the ground's parameters (``ground.friction``, ``ground.normal``; see
``boundaries``).

What it is not for: boundary conditions that project velocities (ground, walls, colliders:
``boundaries`` and the grid update in ``kernels``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import warp as wp

from mosiv_ros.sim.errors import ParameterError
from mosiv_ros.sim.kernels import divide, field_node
from mosiv_ros.sim.params import ParamSpec, param


@dataclass
class GridView:
    """What an ``accelerate`` hook sees: the grid of one substep (index (b * K + k) * G + node).

    Every node with mass is in the box of ``box_dims`` nodes from ``box_lo`` (the whole grid on
    CUDA, the nodes the particles reach on the CPU): a launch of ``n_box`` threads covers it in
    every field, thread t at node ``kernels.field_node(t, box_lo, box_dims, dims)``.
    On a CUDA device of compute capability 9.0 or later ``m`` and ``p`` are strided views of one
    array (``simulator._momentum_and_mass``): a kernel indexes them as any array, but they are
    not contiguous memory.
    """

    m: wp.array  # float, mass
    p: wp.array  # vec3, momentum
    a: wp.array  # vec3, accelerations to add to
    n_batch: int
    n_objects: int
    n_nodes: int
    dims: tuple[int, int, int]
    lo: np.ndarray
    dx: float
    device: str
    box_lo: tuple[int, int, int]
    box_dims: tuple[int, int, int]

    @property
    def n_box(self) -> int:
        return self.n_batch * self.n_objects * int(np.prod(self.box_dims))

    @property
    def box(self) -> list:
        """The launch arguments box_lo, box_dims, dims of ``kernels.field_node``."""
        return [wp.vec3i(*self.box_lo), wp.vec3i(*self.box_dims), wp.vec3i(*self.dims)]


@dataclass
class ParticleView:
    """What a ``stress`` hook sees: the particle state of one substep (index b * N + p)."""

    x: wp.array  # vec3
    v: wp.array  # vec3
    C: wp.array  # mat33, affine velocity field (velocity gradient)
    b: wp.array  # mat33, elastic left Cauchy-Green tensor
    obj: wp.array  # int, object index 0..K-1 of particle p (length N)
    tau: wp.array  # mat33, stresses to add to
    n_batch: int
    n_particles: int
    n_objects: int
    device: str


class Effect:
    """Base class of effects. Subclasses set ``name`` and ``params`` and override a hook.

    ``Effect(**initial)`` sets initial values of the effect's parameters by their short names.
    """

    name: ClassVar[str] = ""
    params: ClassVar[tuple[ParamSpec, ...]] = ()
    doc: ClassVar[str] = ""
    uniform: ClassVar[str] = ""
    """The parameter that is the effect's uniform acceleration, if it is one (module docstring)."""

    def __init__(self, **initial: object) -> None:
        known = {spec.name for spec in self.params}
        unknown = sorted(set(initial) - known)
        if unknown:
            raise ParameterError(
                f"effect {self.name!r}: unknown parameter(s) {', '.join(unknown)}; "
                f"known: {', '.join(sorted(known))}"
            )
        self.initial = dict(initial)

    def specs(self) -> list[ParamSpec]:
        """The parameters with their full names ``<effect>.<param>``."""
        return [
            ParamSpec(f"{self.name}.{s.name}", s.default, s.lower, s.upper, s.unit, s.doc,
                      s.per_object, s.size, s.families)
            for s in self.params
        ]

    @property
    def has_accelerate(self) -> bool:
        return type(self).accelerate is not Effect.accelerate

    @property
    def has_stress(self) -> bool:
        return type(self).stress is not Effect.stress

    def accelerate(self, grid: GridView, values: dict[str, wp.array]) -> None:
        """Add accelerations to ``grid.a`` (override to use)."""

    def stress(self, particles: ParticleView, values: dict[str, wp.array]) -> None:
        """Add Kirchhoff stresses to ``particles.tau`` (override to use)."""

    def time_step_limit(self, values: dict[str, np.ndarray], dx: float, density: float) -> float:
        """Largest stable substep (s) with these parameter values (numpy, by short name)."""
        return math.inf

    def __repr__(self) -> str:
        return f"{type(self).__name__}({', '.join(f'{k}={v!r}' for k, v in self.initial.items())})"


# --- kernels ------------------------------------------------------------------------------------


@wp.kernel
def drag_kernel(
    m: wp.array(dtype=float),
    p: wp.array(dtype=wp.vec3),
    coefficient: wp.array(dtype=float),
    n_nodes: int,
    quadratic: int,
    box_lo: wp.vec3i,
    box_dims: wp.vec3i,
    dims: wp.vec3i,
    a: wp.array(dtype=wp.vec3),
):
    """A -= c v (linear, 1/s) or a -= c |v| v (quadratic, 1/m), c per (batch, object)."""
    i = field_node(wp.tid(), box_lo, box_dims, dims)
    mass = m[i]
    if mass > 0.0:
        v = divide(p[i], mass)  # not p[i] / mass: see kernels.divide
        c = param(coefficient, i // n_nodes, i)
        if quadratic != 0:
            c = c * wp.length(v)
        wp.atomic_add(a, i, -c * v)


@wp.kernel
def kelvin_voigt_kernel(
    C: wp.array(dtype=wp.mat33),
    b: wp.array(dtype=wp.mat33),
    obj: wp.array(dtype=int),
    viscosity: wp.array(dtype=float),
    n_particles: int,
    n_objects: int,
    tau: wp.array(dtype=wp.mat33),
):
    """Tau += J eta_d (C + C^T): a dashpot in parallel with the material (Kelvin-Voigt)."""
    i = wp.tid()
    batch = i // n_particles
    k = obj[i - batch * n_particles]
    J = wp.sqrt(wp.determinant(b[i]))
    eta = param(viscosity, batch * n_objects + k, i)
    wp.atomic_add(tau, i, (C[i] + wp.transpose(C[i])) * (J * eta))


@wp.kernel
def periodic_field_kernel(
    m: wp.array(dtype=float),
    amplitude: wp.array(dtype=float),
    wavelength: wp.array(dtype=float),
    per_batch: int,
    n_nodes: int,
    lo_x: float,
    dx: float,
    box_lo: wp.vec3i,
    box_dims: wp.vec3i,
    dims: wp.vec3i,
    a: wp.array(dtype=wp.vec3),
):
    """A += amplitude sin(2 pi x / wavelength) at every node with mass, x its world x."""
    i = field_node(wp.tid(), box_lo, box_dims, dims)
    if m[i] > 0.0:
        b = i // per_batch
        x = lo_x + dx * float((i % n_nodes) // (dims[1] * dims[2]))
        s = wp.sin(2.0 * wp.pi * x / param(wavelength, b, i))
        g = wp.vec3(param(amplitude, 3 * b, i), param(amplitude, 3 * b + 1, i),
                    param(amplitude, 3 * b + 2, i))
        wp.atomic_add(a, i, g * s)


FIELD_FEATURES = ("1", "x", "y", "z", "x^2", "y^2", "z^2", "x y", "x z", "y z",
                  "vx", "vy", "vz", "|v|", "|v| vx", "|v| vy", "|v| vz")
"""The terms of ``ForceField``: position relative to its origin (m) and velocity (m/s)."""


@wp.func
def field_feature(m: int, r: wp.vec3, v: wp.vec3):
    """Feature ``m`` of ``FIELD_FEATURES`` at relative position r and velocity v."""
    speed = wp.length(v)
    out = 1.0
    if m == 1:
        out = r[0]
    elif m == 2:
        out = r[1]
    elif m == 3:
        out = r[2]
    elif m == 4:
        out = r[0] * r[0]
    elif m == 5:
        out = r[1] * r[1]
    elif m == 6:
        out = r[2] * r[2]
    elif m == 7:
        out = r[0] * r[1]
    elif m == 8:
        out = r[0] * r[2]
    elif m == 9:
        out = r[1] * r[2]
    elif m >= 10 and m <= 12:
        out = v[m - 10]
    elif m == 13:
        out = speed
    elif m >= 14:
        out = speed * v[m - 14]
    return out


@wp.kernel
def force_field_kernel(
    m: wp.array(dtype=float),
    p: wp.array(dtype=wp.vec3),
    w: wp.array(dtype=float),
    origin: wp.array(dtype=float),
    per_batch: int,
    n_nodes: int,
    n_features: int,
    lo: wp.vec3,
    dx: float,
    box_lo: wp.vec3i,
    box_dims: wp.vec3i,
    dims: wp.vec3i,
    a: wp.array(dtype=wp.vec3),
):
    """A += sum_m w_m feature_m(x - origin, v) at every node with mass (x its position)."""
    i = field_node(wp.tid(), box_lo, box_dims, dims)
    mass = m[i]
    if mass > 0.0:
        b = i // per_batch
        node = i % n_nodes
        x = lo + dx * wp.vec3(float(node // (dims[1] * dims[2])), float((node // dims[2]) % dims[1]),
                              float(node % dims[2]))
        r = x - wp.vec3(param(origin, 3 * b, i), param(origin, 3 * b + 1, i), param(origin, 3 * b + 2, i))
        v = divide(p[i], mass)
        total = wp.vec3(0.0, 0.0, 0.0)
        for f in range(n_features):
            k = 3 * (b * n_features + f)
            total += field_feature(f, r, v) * wp.vec3(param(w, k, i), param(w, k + 1, i), param(w, k + 2, i))
        wp.atomic_add(a, i, total)


# --- built-in effects ---------------------------------------------------------------------------


class Gravity(Effect):
    """Uniform gravitational acceleration; a tilted gravity is a different vector."""

    name = "gravity"
    params = (ParamSpec("g", (0.0, 0.0, -9.81), -100.0, 100.0, "m/s^2", "gravity vector", size=3),)
    uniform = "g"


class BodyForce(Effect):
    """A uniform body force per unit mass on every object (e.g. a steady wind), m/s^2."""

    name = "wind"
    params = (ParamSpec("a", (0.0, 0.0, 0.0), -100.0, 100.0, "m/s^2",
                        "body acceleration vector", size=3),)
    uniform = "a"


class LinearDrag(Effect):
    """Linear (Stokes-like) air drag a = -c v, a coefficient per object, 1/s."""

    name = "linear_drag"
    params = (ParamSpec("coefficient", 0.0, 0.0, 1.0e3, "1/s", "linear drag rate", per_object=True),)

    def accelerate(self, grid: GridView, values: dict[str, wp.array]) -> None:
        _drag(grid, values["coefficient"], quadratic=False)

    def time_step_limit(self, values: dict[str, np.ndarray], dx: float, density: float) -> float:
        rate = float(np.max(values["coefficient"]))
        return 0.5 / rate if rate > 0 else math.inf


class QuadraticDrag(Effect):
    """Quadratic air drag a = -c |v| v, c = rho_air C_d A / (2 m) per object, 1/m."""

    name = "drag"
    params = (ParamSpec("coefficient", 0.0, 0.0, 1.0e3, "1/m", "quadratic drag coefficient",
                        per_object=True),)

    def accelerate(self, grid: GridView, values: dict[str, wp.array]) -> None:
        _drag(grid, values["coefficient"], quadratic=True)


class KelvinVoigtDamping(Effect):
    """Internal velocity damping: a viscous stress J eta_d (C + C^T) per object, Pa*s.

    Damps deformation rates (vibration, bouncing) without slowing rigid motion, unlike drag.
    """

    name = "damping"
    params = (ParamSpec("viscosity", 0.0, 0.0, 1.0e5, "Pa*s", "Kelvin-Voigt damping viscosity",
                        per_object=True),)

    def stress(self, particles: ParticleView, values: dict[str, wp.array]) -> None:
        wp.launch(
            kelvin_voigt_kernel,
            dim=particles.n_batch * particles.n_particles,
            inputs=[particles.C, particles.b, particles.obj, values["viscosity"],
                    particles.n_particles, particles.n_objects],
            outputs=[particles.tau],
            device=particles.device,
        )

    def time_step_limit(self, values: dict[str, np.ndarray], dx: float, density: float) -> float:
        # explicit viscous diffusion, as for a fluid: eta dt / (rho dx^2) <= 1 / 6
        eta = float(np.max(values["viscosity"]))
        return density * dx * dx / (6.0 * eta) if eta > 0 else math.inf


class PeriodicField(Effect):
    """A position-dependent body force a sin(2 pi x / wavelength), m/s^2 (x: world x, m).

    A stand-in for forces that vary in space (a fan's jet, a magnet): uniform effects cannot
    reproduce it, so the recorder uses it to test that the loop closure says "unexplained".
    """

    name = "periodic_field"
    params = (ParamSpec("a", (0.0, 0.0, 0.0), -100.0, 100.0, "m/s^2", "amplitude vector", size=3),
              ParamSpec("wavelength", 0.2, 1.0e-3, 1.0e3, "m", "period along world x"))

    def accelerate(self, grid: GridView, values: dict[str, wp.array]) -> None:
        wp.launch(
            periodic_field_kernel,
            dim=grid.n_box,
            inputs=[grid.m, values["a"], values["wavelength"], grid.n_objects * grid.n_nodes,
                    grid.n_nodes, float(grid.lo[0]), grid.dx, *grid.box],
            outputs=[grid.a],
            device=grid.device,
        )


class ForceField(Effect):
    """A smooth external acceleration field: a = sum_m w_m f_m(x - origin, v), m/s^2.

    ``w`` holds a 3-vector per term of ``FIELD_FEATURES`` (constant, linear and quadratic in the
    position, linear in the velocity, the speed, |v| v), term-major. What the loop closure fits
    when free flight shows a force that no named effect explains: a description of the force,
    not a physical model of its cause.
    """

    name = "force_field"
    params = (ParamSpec("w", (0.0,) * (3 * len(FIELD_FEATURES)), -1.0e3, 1.0e3, "m/s^2 per term unit",
                        "coefficients, 3 per term", size=3 * len(FIELD_FEATURES)),
              ParamSpec("origin", (0.0, 0.0, 0.0), -1.0e3, 1.0e3, "m", "where the position terms vanish",
                        size=3))

    def accelerate(self, grid: GridView, values: dict[str, wp.array]) -> None:
        wp.launch(
            force_field_kernel,
            dim=grid.n_box,
            inputs=[grid.m, grid.p, values["w"], values["origin"], grid.n_objects * grid.n_nodes,
                    grid.n_nodes, len(FIELD_FEATURES), wp.vec3(*grid.lo), grid.dx, *grid.box],
            outputs=[grid.a],
            device=grid.device,
        )


def field_features(r: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(n, M) ``FIELD_FEATURES`` at relative positions r (n, 3) and velocities v (n, 3), as the kernel."""
    speed = np.linalg.norm(v, axis=-1)
    x, y, z = r[..., 0], r[..., 1], r[..., 2]
    return np.stack([np.ones_like(x), x, y, z, x * x, y * y, z * z, x * y, x * z, y * z,
                     v[..., 0], v[..., 1], v[..., 2], speed, speed * v[..., 0], speed * v[..., 1],
                     speed * v[..., 2]], axis=-1)


def _drag(grid: GridView, coefficient: wp.array, quadratic: bool) -> None:
    wp.launch(
        drag_kernel,
        dim=grid.n_box,
        inputs=[grid.m, grid.p, coefficient, grid.n_nodes, int(quadratic), *grid.box],
        outputs=[grid.a],
        device=grid.device,
    )


BUILTIN_EFFECTS: dict[str, type[Effect]] = {
    cls.name: cls for cls in (Gravity, BodyForce, LinearDrag, QuadraticDrag, KelvinVoigtDamping,
                               PeriodicField, ForceField)
}
"""Effects by name, for configuration files."""
