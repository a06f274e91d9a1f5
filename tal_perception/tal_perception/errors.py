"""Domain errors of tal_perception. Every message names what was wrong and where.

Run-time input errors (wrong array shapes, NaN twists, out-of-order stamps) use ``PerceptionInputError``,
a ``tal_core.errors.InputError``, so callers that catch the shared input error also catch ours.
"""

from __future__ import annotations

from tal_core.errors import InputError


class TalPerceptionError(Exception):
    """Base class of all tal_perception errors."""


class PerceptionInputError(TalPerceptionError, InputError):
    """A heightmap, twist, gait timing or foothold given to the FEC / VFA is malformed."""


class FecConfigError(TalPerceptionError, ValueError):
    """An invalid foothold-evaluation setting (threshold, margin, sample count); the message names it."""


class LegKinematicsError(TalPerceptionError):
    """The robot's leg structure does not fit the closed-form HAA-HFE-KFE inverse kinematics."""


class VfaInputError(PerceptionInputError):
    """A gait state or heightmap given to the VFA planner is malformed or out of order.

    ``reason`` is a short category (``gait_state_nan``, ``heightmap_out_of_order``, ...) the ``vfa`` node
    counts rejections by.
    """

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


class VpaConfigError(TalPerceptionError, ValueError):
    """An invalid VPA setting (sample grid, RBF count, bounds, horizon); the message names it."""


class VpaModelError(TalPerceptionError):
    """A VPA CNN weights file is missing, corrupt or does not match the settings it is used with."""
