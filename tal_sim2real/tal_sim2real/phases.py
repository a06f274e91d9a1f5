"""Gait phases of a measured experiment: which legs stand when, the phase of each leg at each sample
(stance, swing, touchdown) for localising a residual, and the gait the recording used (for the closed-loop
re-run: a crawl must be re-run as a crawl).

Contacts come from ``/ground_truth/contacts`` when the bag has it, otherwise from the feet's height over
the nominal course (forward kinematics of the measured base pose and joint angles).
"""

from __future__ import annotations

import numpy as np

from tal_core.robot_model import RobotModel

from .measured import MeasuredData

LEG_NAMES = ("LF", "RF", "LH", "RH")
"""Leg order of the joint vector (three joints per leg) and of the contact messages."""
PHASES = ("stance", "swing", "touchdown")
TOUCHDOWN_S = 0.05
"""[s] the first part of a stance after a swing counts as touchdown (impact, loading)."""
CONTACT_DEPTH_M = 0.005
"""[m] a foot closer than this to the nominal ground counts as in contact (kinematic contacts)."""
SETTLE_S = 1.0
MIN_SWING_FRACTION = 0.05
"""A leg that swings less than this fraction of the time does not walk: the gait is a stand."""


def leg_contacts(data: MeasuredData, description=None, nominal=None, every: int = 4) -> np.ndarray:
    """(N, 4) bool: leg in contact at each joint-state sample."""
    n = len(data.t_s)
    if data.contact_in is not None and data.contact_t_s is not None and len(data.contact_t_s):
        idx = np.clip(np.searchsorted(data.contact_t_s, data.t_s, side="right") - 1, 0, len(data.contact_t_s) - 1)
        return np.asarray(data.contact_in, dtype=bool)[idx][:, :4]
    if data.base is None or description is None or nominal is None:
        return np.ones((n, 4), dtype=bool)
    model = RobotModel(description)
    out = np.ones((n, 4), dtype=bool)
    base = data.base
    for start in range(0, n, every):
        model.update(model.make_q(base.position_m[start], base.quat_xyzw[start], data.q_rad[start]), np.zeros(model.nv))
        feet = model.foot_positions()
        ground = np.asarray(nominal.course.height(feet[:, 0], feet[:, 1]))
        out[start : start + every] = feet[:, 2] - description.foot_radius_m - ground < CONTACT_DEPTH_M
    return out


def leg_phases(contacts: np.ndarray, dt_s: float) -> np.ndarray:
    """(N, 4) phase index into PHASES per sample and leg: swing when out of contact, touchdown for the
    first TOUCHDOWN_S of a stance that follows a swing, stance otherwise."""
    n = len(contacts)
    phase = np.where(contacts, 0, 1)
    window = max(1, int(round(TOUCHDOWN_S / dt_s)))
    for leg in range(contacts.shape[1]):
        c = contacts[:, leg]
        touchdowns = np.flatnonzero(c[1:] & ~c[:-1]) + 1
        for i in touchdowns:
            stop = min(i + window, n)
            segment = phase[i:stop, leg]
            segment[segment == 0] = 2
    return phase


def infer_gait(contacts: np.ndarray, t_s: np.ndarray) -> str:
    """Preset gait name ('stand', 'crawl' or 'trot') that the contact pattern shows: no leg swings ->
    stand; mostly one leg in the air at a time -> crawl; pairs of legs swinging together -> trot."""
    walking = contacts[t_s >= t_s[0] + SETTLE_S] if np.any(t_s >= t_s[0] + SETTLE_S) else contacts
    swinging = ~walking
    if swinging.mean(0).max() < MIN_SWING_FRACTION:
        return "stand"
    in_air = swinging.sum(1)
    moving = in_air[in_air > 0]
    return "trot" if np.mean(moving >= 2) >= 0.5 else "crawl"
