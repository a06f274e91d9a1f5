"""Domain errors of tal_control.

Run-time input errors (wrong array sizes, NaN, out-of-order stamps) use ``tal_core.errors.InputError``,
shared by every package; this module holds what is specific to tal_control.
"""

from __future__ import annotations


class TalControlError(Exception):
    """Base class of all tal_control errors."""


class MotionConfigError(TalControlError, ValueError):
    """An invalid motion-generation parameter (gait, swing, foothold or trunk); the message names it."""
