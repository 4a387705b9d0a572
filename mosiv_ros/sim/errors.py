"""Error types of the simulator: bad parameters and runs that diverge.

What it is for: telling a user which object, parameter, frame or setting is at fault.
What it is not for: programming errors (wrong argument types stay TypeError etc.).
"""

from __future__ import annotations


class SimulationError(Exception):
    """Base class of every error the simulator raises on bad input or a failed run."""


class ParameterError(SimulationError, ValueError):
    """A parameter value is out of its valid range, of the wrong shape, or unknown.

    The text names the parameter, the object (when it is a per-object parameter), the value and
    the range it must lie in.
    """


class SimulationDiverged(SimulationError):
    """A rollout produced non-finite or runaway particle states.

    Attributes:
        frame: the frame at whose end the problem was found (1 = after the first frame step).
        object_name: the first object found at fault.
        batch: the batch index of the parameter set at fault.
        reason: what was found, in words.
    """

    def __init__(self, frame: int, object_name: str, batch: int, reason: str) -> None:
        self.frame = frame
        self.object_name = object_name
        self.batch = batch
        self.reason = reason
        super().__init__(str(self))

    def __str__(self) -> str:
        return (
            f"simulation diverged at frame {self.frame}: object {self.object_name!r} "
            f"(parameter set {self.batch}): {self.reason}"
        )

    def __reduce__(self) -> tuple[type[SimulationDiverged], tuple[int, str, int, str]]:
        return (type(self), (self.frame, self.object_name, self.batch, self.reason))
