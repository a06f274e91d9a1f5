"""Torque-path and IMU subsystems of the identification (cheap: no physics re-simulation)."""

from __future__ import annotations

import math

import numpy as np

from .fitting import Fit, effective_samples, fit_scalar, information_criterion
from .imu_bias import estimate_bias, imu_residuals
from .library import CANDIDATES_BY_NAME, LEGS, VARIANTS_BY_NAME, Candidate, Variant
from .measured import MeasuredData, white_noise_std
from .outcomes import (
    ACCEL_BIAS_FLOOR_M_S2,
    GYRO_BIAS_FLOOR_RAD_S,
    IMU_T_STATISTIC,
    Finding,
    Settings,
    SubsystemResult,
)
from .remainder import Remainder, judge, localise
from .torque_path import TorquePathProblem


# -- torque path ------------------------------------------------------------------------------------------
def torque_path_subsystem(
    data: MeasuredData,
    description,
    candidates: list[Candidate],
    id_slice: slice | np.ndarray,
    ho_slice: slice | np.ndarray,
    settings: Settings,
    phases: np.ndarray | None = None,
) -> tuple[SubsystemResult, list[Finding]]:
    """Fit the torque-path candidates on the ``id_slice`` samples (a slice or sample indices) and report the
    gap on ``ho_slice``."""
    problem = TorquePathProblem(data, description)
    r0 = problem.residual({}, id_slice)
    n = len(r0)
    floor = problem.noise_std_nm(id_slice) ** 2 * n
    nominal_cost = float(r0 @ r0)
    dt = data.dt_s

    def cost_of(vals: dict[str, float]) -> float:
        r = problem.residual(vals, id_slice)
        return float(r @ r)

    fits: dict[str, Fit] = {}
    for c in candidates:
        p = c.parameters[0]
        if c.name == "actuator_delay":
            grid = np.arange(0.0, p.upper + 1e-12, dt)
            fits[c.name] = fit_scalar(c, lambda v, name=p.name: cost_of({name: v}), n, grid, integer_step=dt)
        else:
            fits[c.name] = fit_scalar(c, lambda v, name=p.name: cost_of({name: v}), n)
    nominal_fit = Fit((), {}, {}, nominal_cost, n)
    best = min([nominal_fit, *fits.values()], key=lambda f: f.bic())
    # pairs: the best single plus every other candidate (the library has four here, and a single fit of the
    # second effect can rank low while the first one is unmodelled), coordinate descent from the single fits
    if best is not nominal_fit and best.cost > 2.0 * floor:
        for other in sorted(fits.values(), key=lambda f: f.bic()):
            if other.candidates == best.candidates:
                continue
            pair = _coordinate_descent([best, other], candidates, cost_of, n, dt)
            if pair.bic() < best.bic() - settings.min_bic_drop:
                best = pair
    # per-leg variants (issue 34 item 3), tried on the leg holding most of the chosen model's excess
    best, variant = _leg_variants(problem, best, nominal_fit, id_slice, floor, settings, dt)
    accepted = best is not nominal_fit and best.bic() < nominal_fit.bic() - settings.min_bic_drop
    if variant is not None and not accepted:
        variant = None
    reached = problem.max_limit_fraction(id_slice)
    findings = []
    if variant is not None:
        name, where, pname = variant
        findings.append(
            Finding(
                name,
                "torque_path",
                "named",
                {pname: best.values[pname]},
                {pname: best.intervals[pname]},
                best.cost / nominal_cost,
                f"leg {where}"
                + (
                    " on top of the global effect"
                    if CANDIDATES_BY_NAME[VARIANTS_BY_NAME[name].base].parameters[0].name in best.values
                    else " only"
                )
                + "; chosen over the global effect by an information criterion on the effective samples",
                where,
            )
        )
    for c in candidates:
        fit = fits[c.name]
        if accepted and c.name in best.candidates:
            findings.append(
                Finding(
                    c.name,
                    c.subsystem,
                    "named",
                    {k: best.values[k] for k in c.parameter_names},
                    {k: best.intervals.get(k, fit.intervals[c.parameter_names[0]]) for k in c.parameter_names},
                    best.cost / nominal_cost,
                )
            )
        elif c.name == "torque_limit" and reached < 1.0 and fit.values["torque_limit_scale"] >= reached * 0.99:
            findings.append(
                Finding(
                    c.name,
                    c.subsystem,
                    "not_excited",
                    note=(
                        f"commands reached only {100 * reached:.0f}% of the nominal limits: "
                        f"a limit above that leaves no trace; to test it: {c.experiment}"
                    ),
                )
            )
        else:
            findings.append(
                Finding(c.name, c.subsystem, "rejected", fit.values, fit.intervals, fit.cost / nominal_cost)
            )
    named_values = best.values if accepted else {}
    r_ho0 = problem.residual({}, ho_slice)
    r_ho1 = problem.residual(named_values, ho_slice)
    labels = tuple(f"{n}[{variant[1]}]" if variant is not None and n == variant[0] else n for n in best.candidates)
    result = SubsystemResult(
        "torque_path",
        floor,
        nominal_cost,
        best.cost if accepted else nominal_cost,
        float(r_ho0 @ r_ho0),
        float(r_ho1 @ r_ho1),
        problem.noise_std_nm(ho_slice) ** 2 * len(r_ho0),
        labels if accepted else (),
    )
    # the remainder per joint, leg and gait phase against each joint's own torque-sensor noise
    n_joints = problem.effort.shape[1]
    after_el = (r_ho1**2).reshape(-1, n_joints)
    sigma = np.array([white_noise_std(problem.effort[ho_slice][:, j]) for j in range(n_joints)])
    floor_el = np.broadcast_to(sigma**2, after_el.shape).copy()
    result.holdout_floor = float(floor_el.sum())
    result.floor_updated = floor  # the torque sensor noise: the same whatever the model
    remainder = Remainder("torque_path", result.holdout_before, result.holdout_after, result.holdout_floor)
    element_phase = None
    if phases is not None:
        element_phase = phases[np.arange(len(data.t_s))[ho_slice]][:, np.arange(n_joints) // 3]
    localise(
        remainder,
        after_el,
        floor_el,
        {"joint_torque": np.ones(n_joints, dtype=bool)},
        description.joint_names,
        np.arange(n_joints),
        element_phase,
    )
    at_floor = not accepted and nominal_cost < settings.floor_factor * floor
    result.remainder = judge(remainder, result.named, at_floor)
    result.verdict = result.remainder.verdict
    result.channels_before = {"joint_torque_nm": math.sqrt(float(r_ho0 @ r_ho0) / len(r_ho0))}
    result.channels_after = {"joint_torque_nm": math.sqrt(float(r_ho1 @ r_ho1) / len(r_ho1))}
    return result, findings


LEG_VARIANTS = ("leg_torque_gain", "leg_actuator_delay")
"""Per-leg variants of the torque path tried where the remainder points (the sensor-gain variant has the same
torque-path signature as the actuator gain; the dynamics tells them apart, see dynamics.py)."""


def _leg_variants(
    problem: TorquePathProblem,
    best: Fit,
    nominal_fit: Fit,
    id_slice: slice | np.ndarray,
    floor: float,
    settings: Settings,
    dt: float,
) -> tuple[Fit, tuple[str, str, str] | None]:
    """Per-leg variants of the torque path, proposed by the remainder: when the chosen model ``best`` leaves
    more than twice the floor, the leg holding most of its excess gets, for each variant, (a) the leg's own
    value with the global effect removed (the effect is on that leg only) and (b) the leg's own value on top
    of the global effect. The choice between ``best``, the nominal model and these is by an information
    criterion on the effective number of samples (``fitting.effective_samples`` of the lowest-cost option's
    residual, the same for all options), with the usual ``min_bic_drop`` margin to leave ``best``: each extra
    parameter costs log(n_eff), so a global effect stays global. Returns the chosen fit and (variant, leg,
    parameter) when a variant is chosen."""
    if best.cost <= 2.0 * floor:
        return best, None
    r = problem.residual_matrix(best.values, id_slice)
    sigma2 = floor / r.size
    excess = [float(np.sum(r[:, 3 * i : 3 * i + 3] ** 2)) - 3 * len(r) * sigma2 for i in range(len(LEGS))]
    leg = LEGS[int(np.argmax(excess))]
    n = r.size

    def cost_of(vals: dict[str, float]) -> float:
        rr = problem.residual(vals, id_slice)
        return float(rr @ rr)

    options: list[tuple[Fit, tuple[str, str, str] | None]] = [(best, None), (nominal_fit, None)]
    for vname in LEG_VARIANTS:
        variant: Variant = VARIANTS_BY_NAME[vname]
        p = variant.parameter(leg)
        base = CANDIDATES_BY_NAME[variant.base]
        base_param = base.parameters[0].name
        for keep_base in (False, True):
            if keep_base and base_param not in best.values:
                continue
            others = dict(best.values)
            names = list(best.candidates)
            if not keep_base:
                others.pop(base_param, None)
                names = [c for c in names if c != variant.base]
            candidate = variant.candidate(leg)
            if vname == "leg_actuator_delay":
                fit = fit_scalar(
                    candidate,
                    lambda v, o=others, pn=p.name: cost_of({**o, pn: v}),
                    n,
                    np.arange(0.0, p.upper + 1e-12, dt),
                    integer_step=dt,
                )
            else:
                fit = fit_scalar(candidate, lambda v, o=others, pn=p.name: cost_of({**o, pn: v}), n)
            intervals = {k: v for k, v in best.intervals.items() if k in others}
            intervals.update(fit.intervals)
            options.append(
                (
                    Fit((*names, vname), {**others, **fit.values}, intervals, fit.cost, n, fit.evaluations),
                    (vname, leg, p.name),
                )
            )
    lowest = min(options, key=lambda o: o[0].cost)[0]
    n_eff = effective_samples(problem.residual_matrix(lowest.values, id_slice))

    def ic(fit: Fit) -> float:
        return information_criterion(fit.cost, n_eff, fit.n_params)

    incumbent = ic(best)
    chosen = min(options, key=lambda o: ic(o[0]))
    if chosen[1] is None or ic(chosen[0]) >= incumbent - settings.min_bic_drop:
        return best, None
    return chosen


def _coordinate_descent(
    singles: list[Fit], candidates: list[Candidate], cost_of, n: int, dt: float, rounds: int = 3
) -> Fit:
    by_name = {c.name: c for c in candidates}
    names = [name for f in singles for name in f.candidates]
    values = {k: v for f in singles for k, v in f.values.items()}
    intervals = {k: v for f in singles for k, v in f.intervals.items()}
    evaluations = 0
    cost = math.inf
    for _ in range(rounds):
        for name in names:
            c = by_name[name]
            p = c.parameters[0]
            others = {k: v for k, v in values.items() if k != p.name}
            grid = np.arange(0.0, p.upper + 1e-12, dt) if name == "actuator_delay" else None
            fit = fit_scalar(
                c,
                lambda v, others=others, pname=p.name: cost_of({**others, pname: v}),
                n,
                grid,
                integer_step=dt if name == "actuator_delay" else None,
            )
            values[p.name] = fit.values[p.name]
            intervals[p.name] = fit.intervals[p.name]
            evaluations += fit.evaluations
            cost = fit.cost
    return Fit(tuple(names), values, intervals, cost, n, evaluations)


# -- IMU --------------------------------------------------------------------------------------------------
def imu_subsystem(
    data: MeasuredData, candidate: Candidate, id_slice: slice, ho_slice: slice
) -> tuple[SubsystemResult, list[Finding]]:
    gyro, accel = imu_residuals(data, id_slice)
    g_est, a_est = estimate_bias(gyro, data.dt_s), estimate_bias(accel, data.dt_s)
    t_g = np.abs(g_est.mean) / g_est.standard_error
    t_a = np.abs(a_est.mean) / a_est.standard_error
    significant = bool(
        np.any((t_g > IMU_T_STATISTIC) & (np.abs(g_est.mean) > GYRO_BIAS_FLOOR_RAD_S))
        or np.any((t_a > IMU_T_STATISTIC) & (np.abs(a_est.mean) > ACCEL_BIAS_FLOOR_M_S2))
    )
    values = {
        **{f"imu_gyro_bias_{a}_rad_s": float(v) for a, v in zip("xyz", g_est.mean)},
        **{f"imu_accel_bias_{a}_m_s2": float(v) for a, v in zip("xyz", a_est.mean)},
    }
    se = np.concatenate([g_est.standard_error, a_est.standard_error])
    intervals = {k: (v - 1.96 * s, v + 1.96 * s) for (k, v), s in zip(values.items(), se)}
    gyro_h, accel_h = imu_residuals(data, ho_slice)
    scale = np.array([GYRO_BIAS_FLOOR_RAD_S] * 3 + [ACCEL_BIAS_FLOOR_M_S2 * 5] * 3)  # per-axis weights

    def cost(g: np.ndarray, a: np.ndarray, bias: np.ndarray) -> float:
        means = np.concatenate([g.mean(0), a.mean(0)]) - bias
        return float(np.sum((means / scale) ** 2))

    bias = np.array(list(values.values())) if significant else np.zeros(6)
    floor_ho = float(
        np.sum(
            (
                np.concatenate(
                    [estimate_bias(gyro_h, data.dt_s).standard_error, estimate_bias(accel_h, data.dt_s).standard_error]
                )
                / scale
            )
            ** 2
        )
    )
    result = SubsystemResult(
        "imu",
        float(np.sum((se / scale) ** 2)),
        cost(gyro, accel, np.zeros(6)),
        cost(gyro, accel, bias),
        cost(gyro_h, accel_h, np.zeros(6)),
        cost(gyro_h, accel_h, bias),
        max(floor_ho, 1e-12),
        (candidate.name,) if significant else (),
    )
    result.verdict = "named imu_bias" if significant else "no missing effect (bias within its standard error)"
    result.channels_before = {
        "gyro_mean_rad_s": float(np.linalg.norm(gyro_h.mean(0))),
        "accel_mean_m_s2": float(np.linalg.norm(accel_h.mean(0))),
    }
    result.channels_after = {
        "gyro_mean_rad_s": float(np.linalg.norm(gyro_h.mean(0) - bias[:3])),
        "accel_mean_m_s2": float(np.linalg.norm(accel_h.mean(0) - bias[3:])),
    }
    status = "named" if significant else "rejected"
    return result, [
        Finding(
            candidate.name,
            candidate.subsystem,
            status,
            values,
            intervals,
            note=f"largest t-statistic {max(t_g.max(), t_a.max()):.1f}",
        )
    ]
