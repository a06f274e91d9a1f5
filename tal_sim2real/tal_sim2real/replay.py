"""Re-runs of a measured experiment in simulation for the report: held-out open-loop segments (overlay)
and the closed loop with the same controller (sWBC on ground truth) and the recorded velocity commands."""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing
import pickle

import numpy as np
from tal_lab.closed_loop import ClosedLoopConfig, run_closed_loop

from tal_core.robot_description import load_robot_description

from .identify import Identification
from .measured import MeasuredData, load_measured
from .model import SimModel
from .phases import infer_gait, leg_contacts
from .segments import SegmentSimulator, measured_vectors, plan_segments

LOG = logging.getLogger("tal.sim2real.replay")


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
    result: Identification,
    data: MeasuredData | None = None,
    gait: str | None = None,
    nominal_run: BackgroundRerun | None = None,
) -> dict[str, np.ndarray]:
    """The whole experiment re-run in closed loop with the nominal and the updated model, in the gait the
    recording shows (``gait`` overrides it; a crawl re-run as a trot would compare unlike runs); base
    position [m] over time and its RMS error against the measured base. ``nominal_run``: the nominal re-run
    already started in the background (``start_nominal_rerun``, while the identification ran); used when it
    is the same run (its config equals this one's) and finished without error, else it is run here."""
    description = load_robot_description(result.nominal.robot)
    if data is None:
        data = load_measured(result.bag, description)
    if data.cmd_vel is None or data.base is None:
        return {}
    gait = gait or result.gait or infer_gait(leg_contacts(data, description, result.nominal), data.t_s)
    out: dict[str, np.ndarray] = {
        "measured_t": data.t_s - data.t_s[0],
        "measured_pos": data.base.position_m,
        "gait": np.array(gait),
    }
    for key, model in (("nominal", result.nominal), ("updated", result.updated)):
        config = _config(model, _commands(data), data, gait)
        ran = nominal_run.result(config) if key == "nominal" and nominal_run is not None else None
        t, position = ran if ran is not None else _base_path(config)
        out[f"{key}_t"] = t
        out[f"{key}_pos"] = position
        measured = np.stack([np.interp(t, out["measured_t"], data.base.position_m[:, i]) for i in range(3)], 1)
        out[f"{key}_rms_m"] = np.array(float(np.sqrt(np.mean(np.sum((position - measured) ** 2, 1)))))
    return out


class BackgroundRerun:
    """A closed-loop re-run in a process of its own (spawned: nothing of this process's PyBullet worlds is
    copied), started before the identification so that the two share the machine's cores; ``result``
    waits for it. A re-run repeats bit for bit wherever it runs (tal_sim2real/test/test_segment_replay.py)."""

    def __init__(self, config: ClosedLoopConfig) -> None:
        context = multiprocessing.get_context("spawn")
        self.config = config
        self._receive, send = context.Pipe(duplex=False)
        self._process = context.Process(target=_base_path_to, args=(config, send), daemon=True)
        self._process.start()
        send.close()

    def result(self, config: ClosedLoopConfig) -> tuple[np.ndarray, np.ndarray] | None:
        """(t [s], base position [m]) of the re-run if it is ``config``'s and succeeded, else None."""
        if not _same_run(config, self.config):
            return None
        try:
            status, *payload = self._receive.recv()
        except (EOFError, OSError):
            status, payload = "error", ["the re-run's process ended without an answer"]
        finally:
            self.close()
        if status != "ok":
            LOG.warning("closed-loop re-run in the background failed (%s): running it here", payload[0])
            return None
        return payload[0], payload[1]

    def close(self) -> None:
        """Stop the re-run if it still runs (the identification failed) and release its process."""
        if self._process.is_alive():
            self._process.terminate()
        self._process.join()
        self._receive.close()


def start_nominal_rerun(model: SimModel, data: MeasuredData, gait: str | None = None) -> BackgroundRerun | None:
    """Start ``closed_loop_rerun``'s nominal re-run in the background (None when there is nothing to re-run:
    no velocity commands or no base state). ``gait``: as ``closed_loop_rerun``'s; None: the recording's,
    read from its contacts as ``identify`` reads it."""
    if data.cmd_vel is None or data.base is None:
        return None
    description = load_robot_description(model.robot)
    gait = gait or infer_gait(leg_contacts(data, description, model), data.t_s)
    return BackgroundRerun(_config(model, _commands(data), data, gait))


def _same_run(a: ClosedLoopConfig, b: ClosedLoopConfig) -> bool:
    fields = ("gait", "commands", "duration_s", "robot", "initial_xy")
    if any(getattr(a, f) != getattr(b, f) for f in fields):
        return False
    return a.effects == b.effects and pickle.dumps(a.course) == pickle.dumps(b.course)


def _base_path(config: ClosedLoopConfig) -> tuple[np.ndarray, np.ndarray]:
    log = run_closed_loop(config)
    return log.t, log.base_position


def _base_path_to(config: ClosedLoopConfig, send) -> None:
    """Child process of ``BackgroundRerun``: the re-run's (t, base position) or the error, through ``send``."""
    try:
        send.send(("ok", *_base_path(config)))
    except Exception as exc:  # reported in the parent, which then runs it itself
        send.send(("error", f"{type(exc).__name__}: {exc}"))
    finally:
        send.close()


def _commands(data: MeasuredData) -> list[tuple[float, float, float, float]]:
    """The recorded velocity commands as piecewise-constant segments (t from the start [s], vx, vy, yaw rate)."""
    assert data.cmd_vel is not None and data.cmd_vel_t_s is not None
    commands = [
        (float(t - data.t_s[0]), float(v[0]), float(v[1]), float(v[2])) for t, v in zip(data.cmd_vel_t_s, data.cmd_vel)
    ]
    return [commands[0]] + [c for prev, c in zip(commands, commands[1:]) if c[1:] != prev[1:]]


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
