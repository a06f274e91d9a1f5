"""Re-runs of a measured experiment in simulation for the report: held-out open-loop segments (overlay)
and the closed loop with the same controller (sWBC on ground truth) and the recorded velocity commands."""

from __future__ import annotations

import dataclasses

import numpy as np
from tal_lab.closed_loop import ClosedLoopConfig, run_closed_loop

from tal_core.robot_description import load_robot_description

from .identify import Identification
from .measured import MeasuredData, load_measured
from .model import SimModel
from .phases import infer_gait, leg_contacts
from .segments import SegmentSimulator, measured_vectors, plan_segments


def holdout_overlay(result: Identification, data: MeasuredData | None = None, joint: int = 8) -> dict[str, np.ndarray]:
    """Back-to-back 0.1 s open-loop segments over the first second of the held-out window."""
    description = load_robot_description(result.nominal.robot)
    if data is None:
        data = load_measured(result.bag, description)
    start = result.windows_s["holdout"][0]
    plan = plan_segments(data, start, min(start + 1.0, result.windows_s["holdout"][1]), 0.1, 0.1)
    plan = dataclasses.replace(plan, sample_every=1)  # every step, for a continuous plot
    sim = SegmentSimulator(description, data, "effort" if data.effort_nm is not None else "command")
    try:
        before = sim.predict(result.nominal, plan)
        after = sim.predict(result.updated, plan)
    finally:
        sim.close()
    measured = measured_vectors(data, plan)
    idx = plan.starts[:, None] + plan.sample_offsets[None, :]
    out = {"t_s": data.t_s[idx].ravel(), "joint": np.array(description.joint_names[joint])}
    for key, values in (("measured", measured), ("nominal", before), ("updated", after)):
        out[f"{key}_qd"] = values[..., 25 + joint].ravel()
        out[f"{key}_z"] = values[..., 2].ravel()
    return out


def closed_loop_rerun(
    result: Identification, data: MeasuredData | None = None, gait: str | None = None
) -> dict[str, np.ndarray]:
    """The whole experiment re-run in closed loop with the nominal and the updated model, in the gait the
    recording shows (``gait`` overrides it; a crawl re-run as a trot would compare unlike runs); base
    position [m] over time and its RMS error against the measured base."""
    description = load_robot_description(result.nominal.robot)
    if data is None:
        data = load_measured(result.bag, description)
    if data.cmd_vel is None or data.base is None:
        return {}
    commands = [
        (float(t - data.t_s[0]), float(v[0]), float(v[1]), float(v[2])) for t, v in zip(data.cmd_vel_t_s, data.cmd_vel)
    ]
    compact = [commands[0]] + [c for prev, c in zip(commands, commands[1:]) if c[1:] != prev[1:]]
    gait = gait or result.gait or infer_gait(leg_contacts(data, description, result.nominal), data.t_s)
    out: dict[str, np.ndarray] = {
        "measured_t": data.t_s - data.t_s[0],
        "measured_pos": data.base.position_m,
        "gait": np.array(gait),
    }
    for key, model in (("nominal", result.nominal), ("updated", result.updated)):
        config = _config(model, compact, data, gait)
        log = run_closed_loop(config)
        out[f"{key}_t"] = log.t
        out[f"{key}_pos"] = log.base_position
        measured = np.stack([np.interp(log.t, out["measured_t"], data.base.position_m[:, i]) for i in range(3)], 1)
        out[f"{key}_rms_m"] = np.array(float(np.sqrt(np.mean(np.sum((log.base_position - measured) ** 2, 1)))))
    return out


def _config(model: SimModel, commands: list, data: MeasuredData, gait: str) -> ClosedLoopConfig:
    assert data.base is not None
    return ClosedLoopConfig(
        name="sim2real_rerun",
        course=model.course,
        gait=gait,
        commands=tuple(commands),
        duration_s=float(data.t_s[-1] - data.t_s[0]),
        effects=model.effects,
        robot=model.robot,
        initial_xy=(float(data.base.position_m[0, 0]), float(data.base.position_m[0, 1])),
        progress=False,
    )
