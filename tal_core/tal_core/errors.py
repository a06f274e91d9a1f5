"""Domain errors of tal_core. Every message names what was wrong and where."""

from __future__ import annotations


class TalCoreError(Exception):
    """Base class of all tal_core errors."""


class RobotConfigError(TalCoreError):
    """A robot URDF or robot YAML is missing, malformed or inconsistent."""


class CourseConfigError(TalCoreError):
    """A terrain course YAML is invalid. The message names the file, the patch and the field."""


class InputError(TalCoreError):
    """Run-time input (arrays, names, stamps) has the wrong size, unknown names or non-finite values."""
