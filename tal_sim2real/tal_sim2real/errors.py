"""Domain errors of the sim-vs-measured workflow."""

from __future__ import annotations


class Sim2RealError(RuntimeError):
    """Base class of tal_sim2real errors."""


class MeasuredDataError(Sim2RealError):
    """A measured bag cannot be used: unreadable, empty, unknown joints, inconsistent stamps or units."""


class MissingSignalsError(Sim2RealError):
    """A step needs signals the bag does not carry (the message names them)."""

    def __init__(self, what: str, missing: list[str]) -> None:
        super().__init__(f"{what} needs {', '.join(missing)}, which the bag lacks")
        self.what = what
        self.missing = list(missing)


class ModelConfigError(Sim2RealError):
    """A model configuration (sim_bridge parameter YAML) is invalid."""
