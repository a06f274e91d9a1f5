"""Motion generation for the whole-body controller (pure Python, no ROS): gait scheduling with load
ramps, swing trajectories, Raibert footholds and trunk references (after the reactive controller
framework of Barasuol et al. 2013 used in Fahmi 2021, ch. 3)."""

from .footholds import (
    DEFAULT_K_FEEDBACK,
    hip_at_touchdown,
    nominal_foothold,
    raibert_footholds_xy,
    terrain_height,
    terrain_normal,
)
from .gait import CRAWL, PRESETS, STAND, TROT, GaitParameters, GaitPhase, GaitScheduler
from .generator import MeasuredState, MotionGenerator, MotionParameters, MotionTargets
from .swing import SwingSample, SwingTrajectory
from .trunk import FeetMotion, TrunkOscillation, TrunkParameters, TrunkReference, TrunkTarget, rotation_rpy

__all__ = [
    "CRAWL", "DEFAULT_K_FEEDBACK", "PRESETS", "STAND", "TROT", "FeetMotion", "GaitParameters", "GaitPhase",
    "GaitScheduler", "MeasuredState", "MotionGenerator", "MotionParameters", "MotionTargets", "SwingSample",
    "SwingTrajectory", "TrunkOscillation", "TrunkParameters", "TrunkReference", "TrunkTarget", "hip_at_touchdown",
    "nominal_foothold", "raibert_footholds_xy", "rotation_rpy", "terrain_height", "terrain_normal",
]
