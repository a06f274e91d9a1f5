"""Offline closed-loop experiments (no ROS): the controller in the loop with the PyBullet simulation.

``closed_loop`` is the reusable runner (``run_closed_loop``); ``swbc_experiments`` the sWBC acceptance
runs and the thesis analyses (``python -m tal_control.experiments.swbc_experiments``).
"""

from .closed_loop import ClosedLoopConfig, ClosedLoopLog, TickContext, run_closed_loop

__all__ = ["ClosedLoopConfig", "ClosedLoopLog", "TickContext", "run_closed_loop"]
