"""sWBC experiments: acceptance runs and the thesis' passive-WBC analyses (Fahmi 2021, sWBC results).

    python -m tal_lab.swbc_experiments [--quick] [--out results/swbc] [--jobs N]

A. Acceptance (rigid flat ground unless stated): stand, crawl 0.1 m/s, trot 0.3 m/s, trot turning
   (0.2 m/s, 0.3 rad/s), trot over the 15 degree ramp course. Table ``acceptance.md``/``.json`` and one
   PNG per run.
B. Thesis analyses (``analyses.md``/``.json`` and PNGs):
   1. 26 N m limit on LF-KFE during a crawl: load redistribution to HAA/HFE, trunk tracking (plus a
      45 N m run, the lowest round limit this crawl sustains, for comparison).
   2. raised lower limit of LH-HFE during a crawl: slacks engage, the joint is clamped, foot tracking.
   3. ground friction 0.4 with the WBC assuming mu = 1.0 vs mu = 0.4: stance-foot slip (plus mu = 1.0
      with the stance task switched on, K_st/D_st below: the WbcGains default is K_st = D_st = 0).

The simulated actuators have only a global torque-limit scale (``ModelEffects``), so the 26 N m limit
is applied in the WBC (``WbcSettings.torque_limit_overrides_nm``) and, on the simulator side, by
clipping the controller's command before it reaches the bridge (``TorqueClip``); the bridge's own
saturation stays at the robot's limits. Every run is deterministic; ``--jobs`` only changes wall time.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402

from tal_control.wbc import WbcGains, WbcSettings  # noqa: E402
from tal_lab.closed_loop import (  # noqa: E402
    ClosedLoopConfig,
    ClosedLoopLog,
    TickContext,
    run_closed_loop,
    stance_slip,
    tracking_metrics,
)

SETTLE_S = 2.0
KFE_JOINT, KFE_LIMIT_NM, KFE_FEASIBLE_LIMIT_NM = "lf_kfe_joint", 26.0, 45.0
LH_HFE_JOINT, LH_HFE_LOWER_RAD = "lh_hfe_joint", -1.05  # nominal range [-1.222, 0.873]; swing reaches -1.18
AT_LIMIT_TOLERANCE_RAD = 0.01
SLACK_ACTIVE_M_S2 = 0.5
SLIPPERY_MU, WRONG_WBC_MU = 0.4, 1.0
SLIP_SPEED_EVENT_M_S = 0.02
STANCE_TASK_GAINS = {"K_st": 2000.0, "D_st": 90.0}  # [1/s^2], [1/s]; the thesis gives no values
LF, LH = 0, 2


@dataclass(frozen=True)
class TorqueClip:
    """Tick hook: clip the submitted torque of named joints to +-limit [N m] (a weak actuator)."""

    limits: tuple[tuple[str, float], ...]

    def __call__(self, ctx: TickContext) -> np.ndarray:
        names = ctx.controller.model.description.joint_names
        tau = np.array(ctx.output.tau, dtype=float)
        for name, limit in self.limits:
            i = names.index(name)
            tau[i] = float(np.clip(tau[i], -limit, limit))
        return tau


@dataclass(frozen=True)
class Run:
    config: ClosedLoopConfig
    hook: TorqueClip | None = None


def _execute(run: Run) -> ClosedLoopLog:
    return run_closed_loop(run.config, run.hook)


# -- the plan -------------------------------------------------------------------------------------------
def slippery_course(out: Path, mu: float) -> Path:
    """Write a flat rigid course with friction ``mu`` everywhere; returns its path."""
    data = {
        "course": {
            "name": f"flat_rigid_mu{mu:g}",
            "extent": {"x": [-2.0, 10.0], "y": [-2.0, 2.0]},
            "default": {"terrain": "T4", "friction": float(mu), "height_m": 0.0},
            "patches": [],
        }
    }
    path = out / "courses" / f"flat_rigid_mu{mu:g}.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def plan(out: Path, quick: bool) -> tuple[dict[str, Run], list[str]]:
    """All runs by name, and the names of the acceptance runs (in table order)."""

    def d(full: float, short: float) -> float:
        return short if quick else full

    base = ClosedLoopConfig(progress=True)
    runs = {
        "stand": Run(replace(base, name="stand", gait="stand", duration_s=d(10, 3))),
        "crawl": Run(replace(base, name="crawl", gait="crawl", duration_s=d(30, 5), commands=((0.5, 0.1, 0.0, 0.0),))),
        "trot": Run(
            replace(
                base,
                name="trot",
                gait="trot",
                duration_s=d(30, 4),
                initial_xy=(-1.5, 0.0),
                commands=((0.5, 0.3, 0.0, 0.0),),
            )
        ),
        "trot_turn": Run(
            replace(base, name="trot_turn", gait="trot", duration_s=d(20, 4), commands=((0.5, 0.2, 0.0, 0.3),))
        ),
        # Ramp course: up 1-3 m, plateau 3-4 m, down 4-6 m; the run ends with the base near x = 6.7 m.
        "trot_slope": Run(
            replace(
                base,
                name="trot_slope",
                gait="trot",
                course="slope_15deg",
                duration_s=d(38, 5),
                initial_xy=(-0.8, 0.0) if not quick else (0.4, 0.0),
                commands=((0.5, 0.2, 0.0, 0.0),),
            )
        ),
    }
    acceptance = list(runs)
    crawl = runs["crawl"].config
    for limit in (KFE_LIMIT_NM, KFE_FEASIBLE_LIMIT_NM):
        # mu = 1.0 is the simulated ground's true friction: with a limited knee the foot force leans towards
        # the knee axis, and the default mu = 0.8 (inscribed pyramid 0.57) runs out of friction first.
        settings = WbcSettings(friction_coefficient=1.0, torque_limit_overrides_nm=((KFE_JOINT, limit),))
        runs[f"crawl_kfe_limit{limit:g}"] = Run(
            replace(crawl, name=f"crawl_kfe_limit{limit:g}", settings=settings), TorqueClip(((KFE_JOINT, limit),))
        )
    upper = 0.8726646259971648  # the robot's own LH-HFE upper limit (unchanged)
    hfe_settings = WbcSettings(position_limit_overrides_rad=((LH_HFE_JOINT, LH_HFE_LOWER_RAD, upper),))
    runs["crawl_hfe_limit"] = Run(replace(crawl, name="crawl_hfe_limit", settings=hfe_settings))
    course = str(slippery_course(out, SLIPPERY_MU))
    slip = replace(crawl, course=course, commands=((0.5, 0.11, 0.0, 0.0),))
    runs["slip_wbc_mu1.0"] = Run(
        replace(slip, name="slip_wbc_mu1.0", settings=WbcSettings(friction_coefficient=WRONG_WBC_MU))
    )
    runs["slip_wbc_mu0.4"] = Run(
        replace(slip, name="slip_wbc_mu0.4", settings=WbcSettings(friction_coefficient=SLIPPERY_MU))
    )
    runs["slip_wbc_mu1.0_stance_task"] = Run(
        replace(
            slip,
            name="slip_wbc_mu1.0_stance_task",
            settings=WbcSettings(friction_coefficient=WRONG_WBC_MU),
            gains=WbcGains(**STANCE_TASK_GAINS),
        )
    )
    return runs, acceptance


def execute(runs: dict[str, Run], jobs: int) -> dict[str, ClosedLoopLog]:
    names = list(runs)
    if jobs <= 1:
        return {name: _execute(runs[name]) for name in names}
    context = multiprocessing.get_context("fork")
    with ProcessPoolExecutor(max_workers=jobs, mp_context=context) as pool:
        logs = list(pool.map(_execute, [runs[n] for n in names]))
    return dict(zip(names, logs))


# -- helpers --------------------------------------------------------------------------------------------
def _spans(t: np.ndarray, mask: np.ndarray) -> list[tuple[float, float]]:
    """Time intervals where ``mask`` is true."""
    spans, start = [], None
    for ti, m in zip(t, mask):
        if m and start is None:
            start = ti
        elif not m and start is not None:
            spans.append((start, ti))
            start = None
    if start is not None:
        spans.append((start, t[-1]))
    return spans


def _shade(ax, t: np.ndarray, mask: np.ndarray, color: str, label: str | None = None) -> None:
    for i, (a, b) in enumerate(_spans(t, mask)):
        ax.axvspan(a, b, color=color, alpha=0.18, lw=0, label=label if i == 0 else None)


def _finite(value: object) -> object:
    """JSON-safe copy: NaN/inf become None, numpy scalars plain numbers."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if np.isfinite(value) else None
    return value


def _joint(log: ClosedLoopLog, name: str) -> int:
    return list(log.meta["joint_names"]).index(name)  # type: ignore[arg-type]


def _table(headers: list[str], rows: list[list[object]]) -> str:
    def fmt(v: object) -> str:
        return f"{v:.4g}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def _plot_run(log: ClosedLoopLog, path: Path) -> None:
    t = log.t
    fig, axes = plt.subplots(4, 1, figsize=(9, 10), sharex=True)
    for k, c in ((0, "C0"), (1, "C1")):
        axes[0].plot(t, log.base_position[:, k], c, label=f"{'xy'[k]}")
        axes[0].plot(t, log.base_position_des[:, k], c + "--", label=f"{'xy'[k]} desired")
    axes[0].set_ylabel("base x, y [m]")
    axes[1].plot(t, log.base_position[:, 2], "C2", label="z")
    axes[1].plot(t, log.base_position_des[:, 2], "k--", label="z desired")
    axes[1].set_ylabel("base z [m]")
    for k, c in ((0, "C0"), (1, "C1")):
        axes[2].plot(t, log.velocity_h[:, k], c, lw=0.8, label=f"v{'xy'[k]} (base, horizontal)")
        axes[2].plot(t, log.cmd_velocity_h[:, k], c + "--", label=f"v{'xy'[k]} commanded")
    axes[2].set_ylabel("velocity [m/s]")
    axes[3].plot(t, log.velocity_h[:, 2], "C3", lw=0.8, label="yaw rate")
    axes[3].plot(t, log.cmd_velocity_h[:, 2], "k--", label="yaw rate commanded")
    axes[3].set_ylabel("yaw rate [rad/s]")
    axes[3].set_xlabel("time [s]")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left", ncol=2)
    fell = f" FELL at {log.meta['fall_time_s']:.2f} s" if log.fell else ""
    fig.suptitle(f"{log.meta['name']}: {log.meta['gait']} on {log.meta['course']}{fell}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# -- A. acceptance --------------------------------------------------------------------------------------
def acceptance(logs: dict[str, ClosedLoopLog], names: list[str], out: Path) -> dict[str, dict]:
    results, rows = {}, []
    for name in names:
        log = logs[name]
        m = tracking_metrics(log, SETTLE_S)
        m["final_x_m"] = float(log.base_position[-1, 0])
        m["wall_time_s"] = float(log.meta["wall_time_s"])  # type: ignore[arg-type]
        m["real_time_factor"] = float(log.meta["real_time_factor"])  # type: ignore[arg-type]
        results[name] = m
        cmd = log.meta["commands"][-1][1:]  # type: ignore[index]
        cmd_text = f"vx={cmd[0]:g}" + (f", wz={cmd[2]:g}" if cmd[2] else "")
        rows.append(
            [
                name,
                log.meta["course"],
                cmd_text,
                f"{m['sim_time_s']:.0f}",
                "YES" if log.fell else "no",
                1e3 * m["height_mae_m"],
                m["velocity_mae_m_s"],
                m["velocity_vs_command_mae_m_s"],
                f"{m['mean_vx_h_m_s']:.3f} / {m['mean_cmd_vx_h_m_s']:.3f}",
                f"{m['mean_yaw_rate_rad_s']:.3f}",
                f"{np.degrees(m['roll_error_max_rad']):.2f} / {np.degrees(m['pitch_error_max_rad']):.2f}",
                int(m["fallbacks"]),
                m["net_displacement_m"],
                m["path_length_1s_m"],
                m["final_x_m"],
                m["real_time_factor"],
            ]
        )
        _plot_run(log, out / f"acceptance_{name}.png")
    headers = [
        "run",
        "course",
        "cmd [m/s, rad/s]",
        "T [s]",
        "fell",
        "height MAE [mm]",
        "CoM vel. MAE vs ref [m/s]",
        "base vel. MAE vs cmd [m/s]",
        "mean vx / cmd [m/s]",
        "mean yaw rate [rad/s]",
        "max roll / pitch err. [deg]",
        "QP fallbacks",
        "net dist. [m]",
        "path (1 s samples) [m]",
        "final x [m]",
        "RTF",
    ]
    text = (
        "# sWBC acceptance runs\n\nGround-truth base state, 1 kHz physics, WBC at 250 Hz. Errors are "
        f"mean absolute values after {SETTLE_S:g} s. *CoM vel. MAE vs ref*: horizontal CoM velocity vs "
        "the trunk reference (command + crawl CoM shift); *base vel. MAE vs cmd*: base velocity vs the "
        "rate-limited command (includes the gait's designed sway). RTF = simulated / wall time.\n\n"
        + _table(headers, rows)
        + "\n"
    )
    (out / "acceptance.md").write_text(text)
    (out / "acceptance.json").write_text(json.dumps(_finite(results), indent=2))
    return results


# -- B. thesis analyses ---------------------------------------------------------------------------------
def _pre_fall(log: ClosedLoopLog, n: int) -> np.ndarray:
    """Mask over the first ``n`` samples: settled, and at least 0.5 s before a fall."""
    t = log.t[:n]
    end = float(log.meta["fall_time_s"]) - 0.5 if log.fell else np.inf  # type: ignore[arg-type]
    return (t >= SETTLE_S - 1e-9) & (t <= end)


def _trunk_errors(log: ClosedLoopLog, mask: np.ndarray) -> dict[str, float]:
    n = len(mask)
    com = np.linalg.norm(log.com_des[:n][mask] - log.com[:n][mask], axis=1)
    rpy = np.abs(log.rpy_des[:n][mask] - log.base_rpy[:n][mask])
    return {
        "com_error_mean_m": float(np.mean(com)),
        "com_error_max_m": float(np.max(com)),
        "height_mae_m": float(np.mean(np.abs(log.base_position_des[:n][mask, 2] - log.base_position[:n][mask, 2]))),
        "roll_mae_rad": float(np.mean(rpy[:, 0])),
        "pitch_mae_rad": float(np.mean(rpy[:, 1])),
        "roll_error_max_rad": float(np.max(rpy[:, 0])),
        "pitch_error_max_rad": float(np.max(rpy[:, 1])),
    }


def torque_limit_analysis(base: ClosedLoopLog, limited: dict[float, ClosedLoopLog], out: Path) -> dict:
    """Each limited run is compared with the baseline over their common pre-fall window."""
    haa, hfe, kfe = (_joint(base, n) for n in ("lf_haa_joint", "lf_hfe_joint", "lf_kfe_joint"))
    result: dict[str, object] = {
        "note": (
            "limit in the WBC (torque_limit_overrides_nm) and on the simulator side by clipping the submitted "
            "LF-KFE command (TorqueClip); the bridge's actuator model has only a global limit scale. The limited runs "
            "use the WBC friction coefficient 1.0 (the simulated ground's true value). Each limited "
            "run is compared with the unlimited crawl over their common window: settled (t >= 2 s) and, if the "
            "limited run fell, ending 0.5 s before the fall"
        )
    }
    for limit, log in limited.items():
        n = min(len(base.t), len(log.t))
        mask = _pre_fall(log, n)
        entry: dict[str, object] = {
            "limit_nm": limit,
            "fell": log.fell,
            "fall_time_s": log.meta["fall_time_s"],
            "window_s": [float(log.t[:n][mask][0]), float(log.t[:n][mask][-1])],
        }
        for key, run in (("without_limit", base), ("with_limit", log)):
            stance = run.stance[:n, LF] & mask
            tau = run.tau_cmd[:n]
            entry[key] = {
                **_trunk_errors(run, mask),
                "fallbacks": int(np.sum(run.fallback[:n])),
                "max_abs_kfe_cmd_nm": float(np.max(np.abs(tau[:, kfe]))),
                "max_abs_kfe_delivered_nm": float(np.max(np.abs(run.tau_measured[:n, kfe]))),
                "lf_stance_mean_abs_tau_nm": {
                    j: float(np.mean(np.abs(tau[stance, i]))) for j, i in (("HAA", haa), ("HFE", hfe), ("KFE", kfe))
                },
                "lf_stance_fraction_kfe_at_or_above_limit": float(np.mean(np.abs(tau[stance, kfe]) >= limit - 0.1)),
            }
        w, wo = entry["with_limit"], entry["without_limit"]
        entry["hfe_mean_abs_increase_in_lf_stance_nm"] = (
            w["lf_stance_mean_abs_tau_nm"]["HFE"] - wo["lf_stance_mean_abs_tau_nm"]["HFE"]
        )  # type: ignore[index]
        entry["haa_mean_abs_increase_in_lf_stance_nm"] = (
            w["lf_stance_mean_abs_tau_nm"]["HAA"] - wo["lf_stance_mean_abs_tau_nm"]["HAA"]
        )  # type: ignore[index]
        result[f"limit_{limit:g}"] = entry
    # Figure: LF joint torques, LF swing phases shaded (the gait schedule is the same in every run).
    t_end = min(base.t[-1], 10.0)
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    wb = (base.t >= SETTLE_S) & (base.t <= t_end)
    for ax, (label, i) in zip(axes, (("HAA", haa), ("HFE", hfe), ("KFE", kfe))):
        ax.plot(base.t[wb], base.tau_cmd[wb, i], "C7--", lw=1, label="no limit")
        for (limit, log), c in zip(limited.items(), ("C0", "C2")):
            w = (log.t >= SETTLE_S) & (log.t <= t_end)
            fell = f", fell at {log.meta['fall_time_s']:.2f} s" if log.fell else ""
            ax.plot(log.t[w], log.tau_cmd[w, i], c, lw=1.2, label=f"KFE limit {limit:g} N m{fell}")
        _shade(ax, base.t[wb], ~base.stance[wb, LF], "C1", "LF swing")
        ax.set_ylabel(f"LF-{label} torque [N m]")
        ax.grid(alpha=0.3)
    for (limit, _), c in zip(limited.items(), ("C0", "C2")):
        for sign in (1, -1):
            axes[2].axhline(sign * limit, color=c, lw=1.5, ls=":")
    axes[0].legend(fontsize=7, loc="upper right")
    axes[2].set_xlabel("time [s]")
    fig.suptitle("Crawl 0.1 m/s with an artificial torque limit on LF-KFE (shaded: LF swing; dotted: limits)")
    fig.tight_layout()
    fig.savefig(out / "analysis_torque_limit.png", dpi=110)
    plt.close(fig)
    return result


def joint_limit_analysis(base: ClosedLoopLog, limited: ClosedLoopLog, out: Path) -> dict:
    hfe = _joint(base, LH_HFE_JOINT)
    n = min(len(base.t), len(limited.t))
    common = _pre_fall(limited, n)
    result: dict[str, object] = {"lower_limit_rad": LH_HFE_LOWER_RAD}
    for key, log in (("without_limit", base), ("with_limit", limited)):
        swing = ~log.stance[:n, LH] & common
        err = log.foot_position[:n][swing, LH] - log.foot_position_des[:n][swing, LH]
        slack = np.linalg.norm(log.slacks[:n, LH], axis=1)
        q = log.joint_position[:n, hfe]
        at_limit = (q <= LH_HFE_LOWER_RAD + AT_LIMIT_TOLERANCE_RAD) & common
        result[key] = {
            "fell": log.fell,
            "fallbacks": int(np.sum(log.fallback[:n])),
            "lh_swing_rms_error_m": dict(zip("xyz", (float(v) for v in np.sqrt(np.mean(err**2, axis=0))))),
            "lh_swing_max_abs_error_m": dict(zip("xyz", (float(v) for v in np.max(np.abs(err), axis=0)))),
            "lh_hfe_min_rad": float(np.min(q[common])),
            "time_at_or_below_limit_s": float(np.sum(at_limit) * log.dt),
            "time_at_limit_fraction_of_lh_swing": float(np.sum(at_limit & swing) / max(np.sum(swing), 1)),
            "lh_slack_norm_mean_in_swing_m_s2": float(np.mean(slack[swing])),
            "lh_slack_norm_max_m_s2": float(np.max(slack[common])),
            "time_slack_active_s": float(np.sum((slack > SLACK_ACTIVE_M_S2) & common) * log.dt),
            "other_legs_slack_norm_max_m_s2": float(np.max(np.linalg.norm(log.slacks[:n, [0, 1, 3]], axis=2))),
            **_trunk_errors(log, common),
        }
    t0 = 10.0 if limited.t[-1] > 20.0 else SETTLE_S
    w = (limited.t >= t0) & (limited.t <= t0 + 6.0)
    wb = w[:n]
    slack_on = np.linalg.norm(limited.slacks[w, LH], axis=1) > SLACK_ACTIVE_M_S2
    fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    for ax, k in zip((axes[0, 0], axes[0, 1], axes[1, 0]), range(3)):
        ax.plot(limited.t[w], limited.foot_position_des[w, LH, k], "k--", lw=1, label="desired")
        ax.plot(limited.t[w], limited.foot_position[w, LH, k], "C0", lw=1.2, label="actual (raised limit)")
        ax.plot(base.t[:n][wb], base.foot_position[:n][wb, LH, k], "C7:", lw=1, label="actual (nominal limit)")
        ax.set_ylabel(f"LH foot {'xyz'[k]} [m]")
    ax = axes[1, 1]
    ax.plot(limited.t[w], limited.joint_position[w, hfe], "C0", label="LH-HFE (raised limit)")
    ax.plot(base.t[:n][wb], base.joint_position[:n][wb, hfe], "C7:", label="LH-HFE (nominal limit)")
    ax.axhline(LH_HFE_LOWER_RAD, color="k", lw=1.5, label="raised lower limit")
    ax.set_ylabel("LH-HFE [rad]")
    for ax in axes.flat:
        _shade(ax, limited.t[w], slack_on, "C3", f"|slack| > {SLACK_ACTIVE_M_S2:g} m/s^2")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left")
    for ax in axes[1]:
        ax.set_xlabel("time [s]")
    fig.suptitle("Crawl with a raised LH-HFE lower limit (red: LH swing slack active)")
    fig.tight_layout()
    fig.savefig(out / "analysis_joint_limit.png", dpi=110)
    plt.close(fig)
    return result


def _slip_events(speed: np.ndarray, contact: np.ndarray) -> int:
    moving = (speed > SLIP_SPEED_EVENT_M_S) & contact
    return int(
        sum(np.sum(np.diff(moving[:, leg].astype(int)) == 1) + int(moving[0, leg]) for leg in range(moving.shape[1]))
    )


def friction_analysis(runs: dict[str, ClosedLoopLog], out: Path) -> dict:
    result: dict[str, object] = {"ground_mu": SLIPPERY_MU, "stance_task_gains": STANCE_TASK_GAINS}
    fig, axes = plt.subplots(3, 1, figsize=(10, 9), sharex=True)
    for (key, log), c in zip(runs.items(), ("C3", "C0", "C2")):
        slip = stance_slip(log)
        speed = np.linalg.norm(log.foot_slip_velocity[:, :, :2], axis=2)
        contact = log.foot_contact
        fn = np.einsum("nlk,nlk->nl", log.contact_force, log.normals)
        ft = np.linalg.norm(log.contact_force - fn[..., None] * log.normals, axis=2)
        loaded = contact & (fn > 20.0)
        ratio = np.where(loaded, ft / np.maximum(fn, 1e-9), np.nan)
        m = tracking_metrics(log, SETTLE_S)
        cumulative = np.cumsum(np.where(contact, speed, 0.0).sum(axis=1)) * log.dt
        checkpoints = [t for t in (5.0, 10.0, 20.0, 30.0) if t <= log.t[-1] + log.dt + 1e-9]
        result[key] = {
            "wbc_mu": log.meta["friction_coefficient_wbc"],
            "fell": log.fell,
            "fallbacks": int(m["fallbacks"]),
            "total_slip_contact_point_m": float(np.sum(slip["contact_point"])),
            "slip_contact_point_per_leg_m": [float(v) for v in slip["contact_point"]],
            "cumulative_slip_at_m": {f"{t:g}s": float(cumulative[int(round(t / log.dt)) - 1]) for t in checkpoints},
            "slip_after_10s_m": float(cumulative[-1] - cumulative[int(round(10.0 / log.dt)) - 1])
            if log.t[-1] > 10.0
            else None,
            "total_centre_displacement_in_contact_m": float(np.sum(slip["centre"])),
            "max_slip_speed_m_s": float(np.max(np.where(contact, speed, 0.0))),
            "slip_events": _slip_events(speed, contact),
            "true_ft_over_fn_max": float(np.nanmax(ratio)) if np.any(loaded) else float("nan"),
            "time_at_ground_friction_limit_s": float(np.sum(ratio >= 0.95 * SLIPPERY_MU) * log.dt),
            "mean_vx_h_m_s": m["mean_vx_h_m_s"],
            "net_displacement_m": m["net_displacement_m"],
            "com_error_mean_m": m["com_error_mean_m"],
        }
        label = key.replace("slip_", "").replace("_", " ")
        axes[0].plot(log.t, 1e3 * cumulative, c, label=label)
        axes[1].plot(log.t, np.max(np.where(contact, speed, 0.0), axis=1), c, lw=0.8)
        axes[2].plot(log.t, np.nanmax(np.where(np.isnan(ratio), -1.0, ratio), axis=1), c, lw=0.8)
    axes[2].axhline(SLIPPERY_MU, color="k", lw=1.2, label=f"ground mu = {SLIPPERY_MU:g}")
    axes[0].set_ylabel("cumulative stance slip [mm]")
    axes[1].set_ylabel("max stance-foot slip speed [m/s]")
    axes[2].set_ylabel("max true |F_t|/F_n (F_n > 20 N)")
    axes[2].set_ylim(0.0, 1.0)
    axes[2].set_xlabel("time [s]")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    axes[2].legend(fontsize=8)
    fig.suptitle(f"Crawl 0.11 m/s on ground with mu = {SLIPPERY_MU:g}: WBC mu wrong (1.0) vs corrected (0.4)")
    fig.tight_layout()
    fig.savefig(out / "analysis_friction.png", dpi=110)
    plt.close(fig)
    return result


def _b1_rows(b1: dict) -> list[list[object]]:
    rows = []
    for key, entry in b1.items():
        if not key.startswith("limit_"):
            continue
        a, b = entry["without_limit"], entry["with_limit"]
        window = f"{entry['window_s'][0]:.1f}-{entry['window_s'][1]:.1f}"
        for name, r in ((f"no limit ({window} s)", a), (f"{entry['limit_nm']:g} N m ({window} s)", b)):
            tau = r["lf_stance_mean_abs_tau_nm"]
            rows.append(
                [
                    name,
                    "YES" if (r is b and entry["fell"]) else "no",
                    r["fallbacks"],
                    1e3 * r["com_error_mean_m"],
                    1e3 * r["com_error_max_m"],
                    1e3 * r["height_mae_m"],
                    np.degrees(r["roll_error_max_rad"]),
                    np.degrees(r["pitch_error_max_rad"]),
                    r["max_abs_kfe_cmd_nm"],
                    r["max_abs_kfe_delivered_nm"],
                    tau["HAA"],
                    tau["HFE"],
                    tau["KFE"],
                    r["lf_stance_fraction_kfe_at_or_above_limit"],
                ]
            )
    return rows


def analyses_markdown(b1: dict, b2: dict, b3: dict) -> str:
    h1 = [
        "crawl 0.1 m/s (window)",
        "fell",
        "fallbacks",
        "CoM err. mean [mm]",
        "CoM err. max [mm]",
        "height MAE [mm]",
        "roll err. max [deg]",
        "pitch err. max [deg]",
        "max KFE cmd [N m]",
        "max KFE delivered [N m]",
        "LF-HAA mean abs [N m]",
        "LF-HFE mean abs [N m]",
        "LF-KFE mean abs [N m]",
        "LF stance fraction KFE at/above limit",
    ]
    increases = "; ".join(
        f"{e['limit_nm']:g} N m: HFE {e['hfe_mean_abs_increase_in_lf_stance_nm']:+.1f} N m, "
        f"HAA {e['haa_mean_abs_increase_in_lf_stance_nm']:+.1f} N m"
        for k, e in b1.items()
        if k.startswith("limit_")
    )
    rows2 = []
    for k in ("without_limit", "with_limit"):
        r = b2[k]
        e = r["lh_swing_rms_error_m"]
        rows2.append(
            [
                k.replace("_", " "),
                "YES" if r["fell"] else "no",
                r["fallbacks"],
                1e3 * e["x"],
                1e3 * e["y"],
                1e3 * e["z"],
                r["lh_hfe_min_rad"],
                r["time_at_or_below_limit_s"],
                r["time_at_limit_fraction_of_lh_swing"],
                r["lh_slack_norm_mean_in_swing_m_s2"],
                r["lh_slack_norm_max_m_s2"],
                r["time_slack_active_s"],
                np.degrees(r["roll_error_max_rad"]),
                np.degrees(r["roll_mae_rad"]),
                1e3 * r["com_error_mean_m"],
            ]
        )
    h2 = [
        "crawl 0.1 m/s",
        "fell",
        "fallbacks",
        "LH swing RMS x [mm]",
        "y [mm]",
        "z [mm]",
        "min LH-HFE [rad]",
        f"time with LH-HFE <= {LH_HFE_LOWER_RAD + AT_LIMIT_TOLERANCE_RAD:g} rad [s]",
        "fraction of LH swing",
        "LH slack mean in swing [m/s^2]",
        "LH slack max [m/s^2]",
        f"time slack > {SLACK_ACTIVE_M_S2:g} [s]",
        "trunk roll err. max [deg]",
        "roll MAE [deg]",
        "CoM err. mean [mm]",
    ]
    rows3 = []
    for k, r in b3.items():
        if not isinstance(r, dict) or "wbc_mu" not in r:
            continue
        rows3.append(
            [
                k.replace("slip_", "").replace("_", " "),
                "YES" if r["fell"] else "no",
                r["fallbacks"],
                1e3 * r["total_slip_contact_point_m"],
                "-" if r["slip_after_10s_m"] is None else f"{1e3 * r['slip_after_10s_m']:.4g}",
                1e3 * r["total_centre_displacement_in_contact_m"],
                r["max_slip_speed_m_s"],
                r["slip_events"],
                r["true_ft_over_fn_max"],
                r["time_at_ground_friction_limit_s"],
                r["mean_vx_h_m_s"],
                r["net_displacement_m"],
            ]
        )
    h3 = [
        "ground mu 0.4, crawl 0.11 m/s",
        "fell",
        "fallbacks",
        "stance slip total [mm]",
        "slip after t=10 s [mm]",
        "foot-centre displacement in contact [mm]",
        "max slip speed [m/s]",
        f"slip events (> {SLIP_SPEED_EVENT_M_S:g} m/s)",
        "max true Ft/Fn",
        "time Ft/Fn >= 0.95 mu [s]",
        "mean vx [m/s]",
        "net dist. [m]",
    ]
    gains = ", ".join(f"{k} = {v:g}" for k, v in STANCE_TASK_GAINS.items())
    return (
        "# sWBC thesis analyses\n\n"
        f"## B1. Torque limit on LF-KFE (crawl 0.1 m/s)\n\n{b1['note']}.\n\n"
        + _table(h1, _b1_rows(b1))
        + f"\n\nMean |torque| change during LF stance vs no limit: {increases}.\n\n"
        f"## B2. LH-HFE lower limit raised to {LH_HFE_LOWER_RAD:g} rad (crawl 0.1 m/s)\n\n"
        "Foot errors: true foot-sphere centre minus desired, LH swing samples after 2 s.\n\n"
        + _table(h2, rows2)
        + f"\n\n## B3. Ground friction {SLIPPERY_MU:g}, WBC mu {WRONG_WBC_MU:g} vs {SLIPPERY_MU:g}\n\n"
        "Stance slip = integral of the horizontal speed of the foot's material point at the contact while "
        "in true contact (rolling excluded); foot-centre displacement includes the sphere rolling. "
        f"*stance task*: WbcGains {gains} (default gains have the stance task off).\n\n" + _table(h3, rows3) + "\n"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="short runs (3-5 s each) for CI-scale checks")
    parser.add_argument("--out", type=Path, default=Path("results/swbc"), help="output directory")
    parser.add_argument(
        "--jobs",
        type=int,
        default=min(2, os.cpu_count() or 1),
        help="runs in parallel processes (results identical; default: up to 2)",
    )
    parser.add_argument("--save-logs", action="store_true", help="also write every run's log as .npz")
    args = parser.parse_args(argv)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    runs, names = plan(out, args.quick)
    logs = execute(runs, max(1, args.jobs))
    if args.save_logs:
        (out / "logs").mkdir(exist_ok=True)
        for name, log in logs.items():
            log.save_npz(out / "logs" / f"{name}.npz")
    acceptance(logs, names, out)
    b1 = torque_limit_analysis(
        logs["crawl"],
        {limit: logs[f"crawl_kfe_limit{limit:g}"] for limit in (KFE_LIMIT_NM, KFE_FEASIBLE_LIMIT_NM)},
        out,
    )
    b2 = joint_limit_analysis(logs["crawl"], logs["crawl_hfe_limit"], out)
    b3 = friction_analysis(
        {k: logs[k] for k in ("slip_wbc_mu1.0", "slip_wbc_mu0.4", "slip_wbc_mu1.0_stance_task")}, out
    )
    (out / "analyses.md").write_text(analyses_markdown(b1, b2, b3))
    wall = time.perf_counter() - start
    sim = sum(float(log.t[-1] + log.dt) for log in logs.values())
    run_info = {
        "quick": args.quick,
        "jobs": args.jobs,
        "wall_time_s": wall,
        "simulated_s": sim,
        "per_run_wall_s": {k: float(v.meta["wall_time_s"]) for k, v in logs.items()},
    }  # type: ignore[arg-type]
    (out / "analyses.json").write_text(
        json.dumps(_finite({"torque_limit": b1, "joint_limit": b2, "friction": b3, "run": run_info}), indent=2)
    )
    sys.stderr.write(f"done: {len(logs)} runs, {sim:.0f} s simulated in {wall:.0f} s wall -> {out}\n")
    print((out / "acceptance.md").read_text())
    print((out / "analyses.md").read_text())
    return 0 if not any(logs[n].fell for n in names) else 1


if __name__ == "__main__":
    sys.exit(main())
