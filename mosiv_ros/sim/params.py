"""Named, batched, differentiable simulation parameters.

Every continuous quantity the simulator can fit lives here under one name: material parameters
per object (``E``, ``nu``, ...), boundary parameters (``ground.friction``) and effect parameters
(``drag.coefficient``). Each is a flat float32 Warp array with gradients, laid out as
``[batch][object][component]`` (the object axis only for per-object parameters, the component
axis only for vectors), so that a rollout of B parameter sets reads row ``b``.

Kernels read a parameter through its *replicas* (``Parameters[name]``, refreshed once per frame
by ``replicate()``): ``REPLICAS`` copies of every value, of which thread ``tid`` reads copy
``tid % REPLICAS`` (``param(values, index, tid)``). In the adjoint, every read of a parameter
becomes an atomic add into its gradient; a million particles adding into one address every
substep serialise on the GPU (measured: the backward pass ran 9x the forward at 1M particles),
while 128 copies spread them out. The replicate kernel's own adjoint folds the copies back.

Every parameter's values lie in one device array, one after another, and their replicas in
another in the same order, so that one launch replicates them all and one copy brings every
gradient to the host. The host keeps the values too, and reads them there: values change only
through ``set`` and ``update``, and a read from the device waited for the device's queue (a
sample bag's window with its gradient read parameters some 50 times a call, the device idle
meanwhile).

What it is for: storing, broadcasting, validating and reading back values and gradients.
What it is not for: the physics that uses them (``materials``, ``effects``, ``kernels``).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import warp as wp

from mosiv_ros.sim.errors import ParameterError

REPLICAS = 128
_REPLICAS = wp.constant(REPLICAS)


@wp.func
def param(values: wp.array(dtype=float), index: int, tid: int):
    """Value ``index`` of a replicated parameter array, read by thread ``tid``."""
    return values[index * _REPLICAS + tid % _REPLICAS]


@wp.func
def add_param(grads: wp.array(dtype=float), index: int, tid: int, value: float):
    """Add ``value`` to the gradient of the replica ``param(values, index, tid)`` read (its adjoint)."""
    wp.atomic_add(grads, index * _REPLICAS + tid % _REPLICAS, value)


@wp.func
def lane_particle(t: int, part: int, parts: int):
    """The particle that thread ``t`` of part ``part`` of ``parts`` of a launch runs.

    Particle i reads (and in the adjoint adds to) replica i % REPLICAS of every parameter, so
    parts that each take their own REPLICAS / ``parts`` replicas, every particle of them in
    order, add to disjoint gradients in the order one launch adds: they may run side by side
    to the same sums, to the bit. One part (``parts`` = 1) runs particle t.
    """
    lanes = _REPLICAS // parts
    return (t // lanes) * _REPLICAS + part * lanes + t % lanes


def lane_count(total: int, part: int, parts: int) -> int:
    """How many of ``total`` particles part ``part`` of ``parts`` runs (``lane_particle``)."""
    lanes = REPLICAS // parts
    return total // REPLICAS * lanes + min(max(total % REPLICAS - part * lanes, 0), lanes)


@wp.kernel
def _replicate(values: wp.array(dtype=float), out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = values[i // _REPLICAS]


@dataclass(frozen=True)
class ParamSpec:
    """One parameter: its name, default, valid closed range, unit and layout.

    ``families`` restricts a per-object material parameter to the families that use it; range
    checks skip objects of other families (a fluid has no Young's modulus to check).
    """

    name: str
    default: float | tuple[float, ...]
    lower: float
    upper: float
    unit: str
    doc: str
    per_object: bool = False
    size: int = 1
    families: tuple[str, ...] = ()

    def in_range(self, value: float) -> bool:
        """Whether ``value`` is finite and within the bounds as float32 stores them (as values are)."""
        return bool(self.within(value))

    def within(self, values: np.ndarray) -> np.ndarray:
        """``in_range`` of each of ``values``."""
        return np.isfinite(values) & (np.float32(self.lower) <= values) & (values <= np.float32(self.upper))

    def out_of_range(self, value: float, where: str = "") -> ParameterError:
        """The error for a ``value`` not ``in_range``; ``where`` names its object and batch."""
        return ParameterError(
            f"{self.name}{f' of {where}' if where else ''} = {value:g} {self.unit} is out "
            f"of range [{self.lower:g}, {self.upper:g}] {self.unit} ({self.doc})"
        )

    def default_vector(self) -> np.ndarray:
        value = np.atleast_1d(np.asarray(self.default, dtype=np.float64))
        if value.size != self.size:
            raise ValueError(f"{self.name}: default has {value.size} components, not {self.size}")
        return value


class Parameters:
    """Values and gradients of a set of ``ParamSpec`` for B batches and K objects.

    ``families`` gives each object's material family and ``object_names`` its name, both used
    in error messages and to skip range checks of parameters an object's family does not use.
    """

    def __init__(
        self,
        specs: Iterable[ParamSpec],
        n_batch: int,
        object_names: Sequence[str],
        families: Sequence[str],
        device: str,
    ) -> None:
        self.specs = {spec.name: spec for spec in specs}
        self.n_batch = int(n_batch)
        self.object_names = list(object_names)
        self.families = list(families)
        self.device = device
        self._slices: dict[str, slice] = {}
        start = 0
        for spec in self.specs.values():
            size = int(np.prod(self._shape(spec)))
            self._slices[spec.name] = slice(start, start + size)
            start += size
        self._host = np.zeros(start, dtype=np.float32)
        """Every parameter's values, as the device holds them: what ``get`` reads."""
        for spec in self.specs.values():
            self._host[self._slices[spec.name]] = np.broadcast_to(spec.default_vector(), self._shape(spec)).ravel()
        self._values = wp.array(self._host, dtype=float, device=device, requires_grad=True)
        self._replicas = wp.zeros(start * REPLICAS, dtype=float, device=device, requires_grad=True)
        # each parameter's views of the two: written through ``set`` and ``update`` only
        self.arrays: dict[str, wp.array] = {name: self._values[part] for name, part in self._slices.items()}
        self.replicas: dict[str, wp.array] = {
            name: self._replicas[part.start * REPLICAS:part.stop * REPLICAS] for name, part in self._slices.items()}
        self.replicate()

    @property
    def n_objects(self) -> int:
        return len(self.object_names)

    def _shape(self, spec: ParamSpec) -> tuple[int, ...]:
        shape: tuple[int, ...] = (self.n_batch,)
        if spec.per_object:
            shape += (self.n_objects,)
        if spec.size > 1:
            shape += (spec.size,)
        return shape

    def spec(self, name: str) -> ParamSpec:
        try:
            return self.specs[name]
        except KeyError:
            raise ParameterError(
                f"unknown parameter {name!r}; known: {', '.join(sorted(self.specs))}"
            ) from None

    def __contains__(self, name: str) -> bool:
        return name in self.specs

    def __getitem__(self, name: str) -> wp.array:
        """The replicated array kernels read (see ``param``)."""
        self.spec(name)
        return self.replicas[name]

    def replicate(self) -> None:
        """Refresh every parameter's replicas from its values, in one launch (on the tape when recording)."""
        wp.launch(_replicate, dim=self._replicas.shape[0], inputs=[self._values], outputs=[self._replicas],
                  device=self.device)

    def shape(self, name: str) -> tuple[int, ...]:
        """Shape of ``get(name)``: (B,), (B, K), (B, 3) or (B, K, 3)."""
        return self._shape(self.spec(name))

    def set(self, name: str, value: object) -> None:
        """Set a parameter, broadcasting ``value`` to its (B[, K][, 3]) shape.

        A per-object parameter also accepts a mapping from object name to value. Values are
        range-checked for every object whose family uses the parameter.
        """
        self.update({name: value})

    def update(self, values: dict[str, object]) -> None:
        """``set`` each of ``values``, copied to the device at once; none of them if one is refused."""
        host = self._host.copy()
        for name, value in values.items():
            spec = self.spec(name)
            part = self._slices[spec.name]
            host[part] = self._checked(spec, value, host[part].reshape(self._shape(spec))).ravel()
        self._host = host
        self._values.assign(host)

    def _checked(self, spec: ParamSpec, value: object, current: np.ndarray) -> np.ndarray:
        """``value`` of parameter ``spec`` (``set``'s rules) as float32 of its shape, range-checked.

        ``current``: its values so far, which a mapping by object name keeps for the others.
        """
        name, shape = spec.name, self._shape(spec)
        if isinstance(value, dict):
            if not spec.per_object:
                raise ParameterError(f"{name}: a mapping by object name needs a per-object parameter")
            array = current.astype(np.float64)
            for obj_name, obj_value in value.items():
                if obj_name not in self.object_names:
                    raise ParameterError(
                        f"{name}: unknown object {obj_name!r}; objects: {', '.join(self.object_names)}"
                    )
                array[:, self.object_names.index(obj_name)] = obj_value
        else:
            try:
                array = np.broadcast_to(np.asarray(value, dtype=np.float64), shape)
            except ValueError:
                raise ParameterError(
                    f"{name}: cannot broadcast a value of shape {np.shape(value)} to {shape} "
                    f"(batch{', object' if spec.per_object else ''}"
                    f"{', component' if spec.size > 1 else ''})"
                ) from None
        self._check(spec, array)
        return np.asarray(array, dtype=np.float32)

    def get(self, name: str) -> np.ndarray:
        """Current values as float64, shaped as ``shape(name)`` (read on the host)."""
        return self._host[self._slices[self.spec(name).name]].astype(np.float64).reshape(self.shape(name))

    def grads(self) -> dict[str, np.ndarray]:
        """Every parameter's accumulated gradient, shaped as ``shape(name)``, in one copy from the device."""
        every = self._values.grad.numpy().astype(np.float64)
        return {name: every[part].reshape(self.shape(name)) for name, part in self._slices.items()}

    def zero_grad(self) -> None:
        self._values.grad.zero_()
        self.zero_replica_grad()

    def zero_replica_grad(self) -> None:
        """Zero the replicas' gradients: each frame's backward folds them into the values' once."""
        self._replicas.grad.zero_()

    def validate(self) -> None:
        """Range-check every parameter's values (``set`` and ``update`` check what they write)."""
        for spec in self.specs.values():
            self._check(spec, self.get(spec.name))

    def _check(self, spec: ParamSpec, values: np.ndarray) -> None:
        """Raise ``spec.out_of_range`` for the first value (in index order) not ``in_range``.

        Checked as arrays: ``update`` checks every row of what it sets (every parameter of 32
        rows took 0.47 ms of host time an element at a time).
        """
        ok = spec.within(values)
        if spec.per_object and spec.families:  # objects of other families do not use it
            unused = np.array([family not in spec.families for family in self.families])
            ok |= unused.reshape((1, -1) + (1,) * (values.ndim - 2))
        if ok.all():
            return
        index = tuple(int(i) for i in np.argwhere(~ok)[0])
        value = float(values[index])
        obj = index[1] if spec.per_object else None
        where = f"object {self.object_names[obj]!r} ({self.families[obj]})" if obj is not None else ""
        batch = f"parameter set {index[0]}" if self.n_batch > 1 else ""
        raise spec.out_of_range(value, ", ".join(s for s in (where, batch) if s))
