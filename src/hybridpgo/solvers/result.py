"""Solver results (docs/contributing.md#solver-api)."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..graph import FloatArray


class Status(enum.Enum):
    CONVERGED = "converged"
    MAX_ITERATIONS = "max_iterations"
    STALLED = "stalled"
    FAILED = "failed"


MESSAGES: dict[Status, str] = {
    Status.CONVERGED: "converged: the relative energy decrease fell below the tolerance",
    Status.MAX_ITERATIONS: "stopped at the iteration (sweep) limit",
    Status.STALLED: "stalled: no step decreased the energy",
    Status.FAILED: "failed: the solver could not make progress (see warnings)",
}


@dataclass(frozen=True)
class SolveResult:
    """What a solver returns.

    ``energy_history[k]`` is the energy after iteration (sweep) k; ``energy_history[0]`` is the
    initial energy.  ``times[k]`` is the wall time (s, since the start, compile excluded) at which
    ``energy_history[k]`` was reached.
    """

    rotations: FloatArray
    """(N, 3, 3) final R_world_node."""
    translations: FloatArray
    """(N, 3) final t_world_node."""
    status: Status
    iterations: int
    energy_history: FloatArray
    times: FloatArray
    method: str
    num_constraints: int
    timings: dict[str, float] = field(default_factory=dict)
    """Named wall times in seconds, e.g. 'compile', 'analyze', 'solve', 'polish'."""
    stats: dict[str, Any] = field(default_factory=dict)
    """Method-specific statistics (per-constraint times, rejected steps, ...)."""

    @property
    def message(self) -> str:
        return MESSAGES[self.status]

    @property
    def initial_energy(self) -> float:
        return float(self.energy_history[0])

    @property
    def final_energy(self) -> float:
        return float(self.energy_history[-1])

    @property
    def energy_per_constraint(self) -> float:
        return self.final_energy / max(self.num_constraints, 1)

    def summary(self) -> dict[str, Any]:
        """JSON-friendly summary (no pose arrays)."""
        out: dict[str, Any] = {
            "method": self.method,
            "status": self.status.value,
            "message": self.message,
            "iterations": self.iterations,
            "initial_energy": self.initial_energy,
            "final_energy": self.final_energy,
            "energy_per_constraint": self.energy_per_constraint,
            "num_constraints": self.num_constraints,
            "energy_history": [float(e) for e in np.asarray(self.energy_history)],
            "times": [float(t) for t in np.asarray(self.times)],
            "timings": dict(self.timings),
        }
        out.update({k: v for k, v in self.stats.items() if _jsonable(v)})
        return out


def _jsonable(v: Any) -> bool:
    return isinstance(v, (int, float, str, bool, list, dict)) or v is None
