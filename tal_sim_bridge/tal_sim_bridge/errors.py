"""Domain errors of tal_sim_bridge."""

from __future__ import annotations


class SimBridgeError(Exception):
    """Base class of all tal_sim_bridge errors."""


class BridgeConfigError(SimBridgeError, ValueError):
    """An invalid bridge parameter or model-effect setting (the message names the parameter)."""


class CommandRejectedError(SimBridgeError):
    """A joint command was rejected (unknown joint, wrong array size, non-finite value, stale stamp).

    ``reason`` is a short category used for counting rejections in diagnostics.
    """

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason
