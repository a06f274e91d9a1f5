"""Identify the missing effect(s) in a measured bag: residuals per subsystem, screening of the candidate
library, fits by re-simulation, choice by information criterion and a check on validation data.

Time windows of the bag: the first ``settle_s`` are skipped (start-up transients), the last
``holdout_fraction`` are held out (never used to fit or choose, only to report the gap before/after),
and the rest is the identification window. Within it, open-loop segments alternate between fitting and
validation. The torque path (no simulation, so no drift) holds out every ``torque_holdout_every``-th block
of ``torque_block_s`` instead: its excitation (the peak torques) changes over a recording, and a tail can
hold torques the identification window never reached (a torque limit seen only in the held-out part).

Decisions per subsystem (torque path, IMU, dynamics):
  * what remains (``remainder``): the held-out residual of the chosen model against a noise floor
    re-estimated with that model; above ``remainder.REMAINDER_FACTOR`` floors the verdict is "partly
    explained" or "not explained by the library" (never a plain "named"), localised per channel, joint,
    leg and gait phase;
  * named: the fitted effect lowers the Bayesian information criterion by more than ``min_bic_drop`` and
    (dynamics) the validation cost by at least ``min_validation_gain``;
  * no missing effect: the nominal residual is at the noise floor (cost < ``floor_factor`` x floor);
  * not excited: the probe value of the effect would change the residual by less than the noise floor
    (the report says which experiment would show it);
  * missing signals: the effect needs signals the bag lacks (that effect is skipped, not the others).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from tal_core.robot_description import load_robot_description

from .dynamics import dynamics_subsystem
from .library import CANDIDATES, VARIANTS, missing_signals
from .measured import MeasuredData, load_measured
from .model import PARAMETER_NAMES, SimModel
from .outcomes import Finding, Identification, Settings, SubsystemResult
from .phases import infer_gait, leg_contacts, leg_phases
from .subsystems import imu_subsystem, torque_path_subsystem

__all__ = ["Finding", "Identification", "Settings", "SubsystemResult", "identify"]


def identify(
    bag: str | Path, nominal: SimModel, settings: Settings | None = None, data: MeasuredData | None = None
) -> Identification:
    """Run the whole identification on ``bag`` against the ``nominal`` model (``data``: the bag already
    read with ``load_measured``, so that a caller who needs it too reads it once)."""
    settings = settings or Settings()
    started = time.perf_counter()
    description = load_robot_description(nominal.robot)
    if data is None:
        data = load_measured(bag, description)
    t0, t_end = float(data.t_s[0]), float(data.t_s[-1])
    fit_start = t0 + settings.settle_s
    holdout_start = t_end - settings.holdout_fraction * (t_end - t0)
    windows = {"identification": (fit_start, holdout_start), "holdout": (holdout_start, t_end)}
    id_slice = slice(data.index_at(fit_start), data.index_at(holdout_start))
    ho_slice = slice(data.index_at(holdout_start), len(data.t_s))
    torque_id, torque_ho = _interleaved_blocks(data, fit_start, settings)
    available = data.signals()
    contacts = leg_contacts(data, description, nominal)
    phases = leg_phases(contacts, data.dt_s)
    gait = infer_gait(contacts, data.t_s)
    findings: list[Finding] = []
    subsystems: dict[str, SubsystemResult] = {}
    values = nominal.values()
    for candidate in CANDIDATES:
        missing = missing_signals(candidate, available)
        if missing:
            findings.append(
                Finding(
                    candidate.name, candidate.subsystem, "missing_signals", note=f"skipped: needs {', '.join(missing)}"
                )
            )
    skipped = {f.candidate for f in findings}
    usable = [c for c in CANDIDATES if c.name not in skipped]

    torque = [c for c in usable if c.subsystem == "torque_path"]
    if torque:
        result, found = torque_path_subsystem(data, description, torque, torque_id, torque_ho, settings, phases)
        subsystems["torque_path"] = result
        findings += found
    imu = [c for c in usable if c.subsystem == "imu"]
    if imu:
        result, found = imu_subsystem(data, imu[0], id_slice, ho_slice)
        subsystems["imu"] = result
        findings += found
    for f in findings:
        if f.status == "named":
            values.update(_model_values(f.values))
    leg_gain = next((f for f in findings if f.status == "named" and f.candidate == "leg_torque_gain"), None)
    dynamics = [c for c in usable if c.subsystem == "dynamics"]
    steps = 0
    if dynamics:
        result, found, steps = dynamics_subsystem(
            data,
            description,
            dynamics,
            nominal,
            windows,
            settings,
            phases,
            (leg_gain.where, next(iter(leg_gain.values.values()))) if leg_gain is not None else None,
        )
        subsystems["dynamics"] = result
        sensor = next((f for f in found if f.candidate == "leg_torque_sensor_gain"), None)
        if sensor is not None and leg_gain is not None:
            # the dynamics says the leg's measured torques, not its delivered ones, carry the gain: the torque
            # path's per-leg gain is that leg's torque-sensor gain
            found.remove(sensor)
            (key,) = sensor.values
            sensor.intervals = {key: next(iter(leg_gain.intervals.values()), (float("nan"), float("nan")))}
            sensor.cost_ratio = leg_gain.cost_ratio
            findings.remove(leg_gain)
            findings.append(sensor)
            tp = subsystems.get("torque_path")
            if tp is not None:
                tp.named = tuple(sensor.label if n == leg_gain.label else n for n in tp.named)
                if tp.remainder is not None:
                    tp.remainder.verdict = tp.remainder.verdict.replace(leg_gain.label, sensor.label)
                    tp.verdict = tp.remainder.verdict
        findings += found
        for f in found:
            if f.status == "named":
                values.update(_model_values(f.values))
    updated = nominal.with_values(values)
    order = {c.name: i for i, c in enumerate(CANDIDATES)}
    order.update({v.name: len(CANDIDATES) + i for i, v in enumerate(VARIANTS)})
    findings.sort(key=lambda f: order[f.candidate])
    return Identification(
        str(bag),
        nominal,
        updated,
        findings,
        subsystems,
        windows,
        time.perf_counter() - started,
        steps,
        dict(data.rejected),
        gait,
    )


def _model_values(values: dict[str, float]) -> dict[str, float]:
    """The sim_bridge parameters among a finding's values (per-leg and per-joint variants are not: the
    bridge's effects are global; they stay in the report)."""
    return {k: v for k, v in values.items() if k in PARAMETER_NAMES}


def _interleaved_blocks(data: MeasuredData, start_s: float, settings: Settings) -> tuple[np.ndarray, np.ndarray]:
    """Sample indices from ``start_s`` [s] on, split into blocks of ``torque_block_s``: every
    ``torque_holdout_every``-th block held out, the rest for identification."""
    index = np.arange(data.index_at(start_s), len(data.t_s))
    block = ((data.t_s[index] - start_s) // settings.torque_block_s).astype(int)
    held = block % settings.torque_holdout_every == settings.torque_holdout_every - 1
    return index[~held], index[held]
