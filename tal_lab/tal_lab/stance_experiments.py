"""STANCE experiments: the thesis' soft-terrain simulations (Fahmi 2021, STANCE results section).

    python -m tal_lab.stance_experiments [--quick] [--out results/stance] [--jobs N]

Controllers: *sWBC* (rigid contacts), *c3WBC-T2* (compliant contacts with T2's true parameters,
8000 N/m and 400 N s/m, for every leg) and *STANCE* (compliant contacts fed by the online TCE, which uses
the ground-truth base state as the thesis used motion capture; fixed rigid values until a leg's first
estimate). All runs crawl; all are deterministic.

1. GRF tracking: MAE of actual vs optimal normal force of the LF foot in stance at 0.05 m/s on T1, T2, T4.
   The actual force at tick k+1 is compared with the optimum of tick k (the force that command produced).
2. TCE accuracy on the transition course (rigid, T1, T2, T3, rigid; 2 m strips) at 0.1 m/s: mean, std
   and % error per terrain and leg, over samples whose whole window lies on that terrain, plus a plot.
3. Aggressive trunk manoeuvres on T1 (standing; height 0.05 m at 1.8 Hz, roll 0.5 rad at 1.5 Hz):
   stance-foot contact losses and falls, sWBC vs STANCE.
4. Speed ramp on T1, 0.05 -> 0.3 m/s at 0.005 m/s^2: completion or the speed at the fall.
5. Energy on T1 at 0.05, 0.15, 0.25 m/s: integral of sum |tau qd| after the start-up, and per metre.
6. Lateral transition (left feet on T1, right feet on rigid ground): per-leg estimates.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import sys
import time
from collections import deque
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402

from tal_control.motion.trunk import TrunkOscillation  # noqa: E402
from tal_control.wbc import WbcSettings  # noqa: E402
from tal_core.legs import LEGS  # noqa: E402
from tal_core.terrain_patches import TERRAIN_PRESETS  # noqa: E402
from tal_estimation.tce import TceSettings  # noqa: E402
from tal_lab.closed_loop import ClosedLoopConfig, ClosedLoopLog, run_closed_loop  # noqa: E402
from tal_lab.swbc_experiments import _finite, _table  # noqa: E402

LF = 0
SETTLE_S = 3.0
T2 = TERRAIN_PRESETS["T2"]
RIGID = TERRAIN_PRESETS["T4"]
CONTROLLERS = ("swbc", "c3wbc_t2", "stance")
LABELS = {"swbc": "sWBC", "c3wbc_t2": "c3WBC (T2 params)", "stance": "STANCE"}
THESIS_TCE_ERROR = {"T1": 0.9, "T2": 1.4, "T3": 1.1, "T4": 12.0}
TERRAIN_BY_STIFFNESS = {p.stiffness_n_per_m: name for name, p in TERRAIN_PRESETS.items()}
RAMP_START, RAMP_END, RAMP_ACCEL = 0.05, 0.3, 0.005   # [m/s], [m/s], [m/s^2] (thesis)
ENERGY_SPEEDS = (0.05, 0.15, 0.25)
AGGRESSIVE = TrunkOscillation(height_amplitude_m=0.05, height_frequency_hz=1.8, roll_amplitude_rad=0.5,
                              roll_frequency_hz=1.5, start_time_s=2.0)


def controller_config(kind: str, **kwargs: object) -> ClosedLoopConfig:
    """A crawl on ``course`` with one of CONTROLLERS (impedance source and contact model set)."""
    base = {"gait": "crawl", "tce": TceSettings()}
    if kind == "swbc":
        base |= {"settings": WbcSettings(contact_model="rigid"), "impedance_source": "none"}
    elif kind == "c3wbc_t2":
        base |= {"settings": WbcSettings(contact_model="compliant"), "impedance_source": "fixed",
                 "terrain_stiffness_n_per_m": T2.stiffness_n_per_m, "terrain_damping_ns_per_m": T2.damping_ns_per_m}
    elif kind == "stance":
        base |= {"settings": WbcSettings(contact_model="compliant"), "impedance_source": "tce",
                 "terrain_stiffness_n_per_m": RIGID.stiffness_n_per_m,
                 "terrain_damping_ns_per_m": RIGID.damping_ns_per_m}
    else:
        raise ValueError(f"unknown controller {kind!r}")
    return ClosedLoopConfig(**(base | kwargs))  # type: ignore[arg-type]


def write_course(out: Path, name: str, extent_x: tuple[float, float], default: str,
                 patches: list[dict]) -> Path:
    """Write a course YAML under ``out/courses`` and return its path."""
    data = {"course": {"name": name, "extent": {"x": list(extent_x), "y": [-2.0, 2.0]},
                       "default": {"terrain": default, "friction": 1.0, "height_m": 0.0}, "patches": patches}}
    path = out / "courses" / f"{name}.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def ramp_commands(start_s: float) -> tuple[tuple[float, float, float, float], ...]:
    """0.05 -> 0.3 m/s at 0.005 m/s^2 from ``start_s`` [s], as 0.5 s steps (the trunk reference's own
    acceleration limit smooths them)."""
    commands, step_s = [(0.0, RAMP_START, 0.0, 0.0)], 0.5
    n = int(round((RAMP_END - RAMP_START) / RAMP_ACCEL / step_s))
    for i in range(1, n + 1):
        commands.append((start_s + i * step_s, RAMP_START + i * step_s * RAMP_ACCEL, 0.0, 0.0))
    return tuple(commands)


def plan(out: Path, quick: bool) -> dict[str, ClosedLoopConfig]:
    """Every run by name."""
    scale = 0.3 if quick else 1.0
    runs: dict[str, ClosedLoopConfig] = {}
    for terrain, course in (("T1", "flat_t1"), ("T2", "flat_t2"), ("T4", "flat_t4")):
        for kind in CONTROLLERS:
            runs[f"grf_{kind}_{terrain}"] = controller_config(
                kind, name=f"grf_{kind}_{terrain}", course=course, commands=((0.0, 0.05, 0.0, 0.0),),
                duration_s=max(6.0, 15.0 * scale))
    transition = write_course(out, "transition_course", (-2.0, 12.0), "T4", [
        {"name": "soft_t1", "type": "flat", "x": [2.0, 4.0], "terrain": "T1"},
        {"name": "moderate_t2", "type": "flat", "x": [4.0, 6.0], "terrain": "T2"},
        {"name": "stiff_t3", "type": "flat", "x": [6.0, 8.0], "terrain": "T3"}])
    runs["tce_transition"] = controller_config(
        "stance", name="tce_transition", course=transition, initial_xy=(1.0, 0.0),
        commands=((0.0, 0.1, 0.0, 0.0),), duration_s=30.0 if quick else 82.0)
    for kind in ("swbc", "stance"):
        runs[f"aggressive_{kind}"] = controller_config(
            kind, name=f"aggressive_{kind}", course="flat_t1", gait="stand", trunk_oscillation=AGGRESSIVE,
            duration_s=max(5.0, 12.0 * scale), stop_on_fall=True)
    long_t1 = write_course(out, "flat_t1_long", (-2.0, 16.0), "T1", [])
    ramp_start = 2.0
    ramp_duration = ramp_start + (RAMP_END - RAMP_START) / RAMP_ACCEL + 5.0
    for kind in ("swbc", "stance"):
        runs[f"ramp_{kind}"] = controller_config(
            kind, name=f"ramp_{kind}", course=long_t1, initial_xy=(-1.0, 0.0),
            commands=ramp_commands(ramp_start), duration_s=ramp_duration * (0.25 if quick else 1.0))
    for speed in ENERGY_SPEEDS:
        for kind in ("swbc", "stance"):
            runs[f"energy_{kind}_{speed:g}"] = controller_config(
                kind, name=f"energy_{kind}_{speed:g}", course=long_t1, initial_xy=(-1.0, 0.0),
                commands=((0.0, speed, 0.0, 0.0),), duration_s=max(6.0, 15.0 * scale))
    lateral = write_course(out, "lateral_t1_rigid", (-2.0, 10.0), "T4", [
        {"name": "soft_left", "type": "flat", "x": [-2.0, 10.0], "y": [0.0, 2.0], "terrain": "T1"}])
    runs["lateral"] = controller_config("stance", name="lateral", course=lateral,
                                        commands=((0.0, 0.05, 0.0, 0.0),), duration_s=max(8.0, 15.0 * scale))
    return runs


def _execute(config: ClosedLoopConfig) -> ClosedLoopLog:
    return run_closed_loop(config)


def execute(runs: dict[str, ClosedLoopConfig], jobs: int) -> dict[str, ClosedLoopLog]:
    """Run everything, longest first so two workers finish together."""
    names = sorted(runs, key=lambda n: -runs[n].duration_s)
    if jobs <= 1:
        logs = [_execute(runs[n]) for n in names]
    else:
        with ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("fork")) as pool:
            logs = list(pool.map(_execute, [runs[n] for n in names]))
    return dict(zip(names, logs))


# -- 1. GRF tracking -------------------------------------------------------------------------------------
def grf_error(log: ClosedLoopLog, leg: int = LF, settle_s: float = SETTLE_S) -> dict[str, float]:
    """MAE [N] of the actual normal force at tick k+1 against the WBC's optimum at tick k, while the leg
    is a planned and true stance leg at both ticks, after ``settle_s``."""
    n = log.normals[:-1, leg]
    optimal = np.einsum("ij,ij->i", log.wbc_forces[:-1, leg], n)
    actual = np.einsum("ij,ij->i", log.contact_force[1:, leg], n)
    mask = (log.stance[:-1, leg] & log.stance[1:, leg] & log.foot_contact[1:, leg] & (log.t[:-1] >= settle_s))
    if not mask.any():
        return {"mae_n": float("nan"), "max_n": float("nan"), "samples": 0}
    signed = actual[mask] - optimal[mask]
    error = np.abs(signed)
    return {"mae_n": float(np.mean(error)), "max_n": float(np.max(error)), "samples": int(mask.sum()),
            "bias_n": float(np.mean(signed)), "std_n": float(np.std(signed)),
            "mean_force_n": float(np.mean(actual[mask]))}


def grf_analysis(logs: dict[str, ClosedLoopLog], out: Path) -> dict:
    result: dict[str, dict] = {}
    for terrain in ("T1", "T2", "T4"):
        result[terrain] = {kind: grf_error(logs[f"grf_{kind}_{terrain}"]) | {
            "fell": logs[f"grf_{kind}_{terrain}"].fell} for kind in CONTROLLERS}
        result[terrain]["best"] = min(CONTROLLERS, key=lambda k: result[terrain][k]["mae_n"])
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    width = 0.25
    for i, kind in enumerate(CONTROLLERS):
        values = [result[t][kind]["mae_n"] for t in ("T1", "T2", "T4")]
        axes[0].bar(np.arange(3) + (i - 1) * width, values, width, label=LABELS[kind])
    axes[0].set_xticks(range(3), ["T1 (3500 N/m)", "T2 (8000 N/m)", "T4 (rigid)"])
    axes[0].set_ylabel("LF normal GRF MAE [N]")
    axes[0].set_title("GRF tracking, crawl 0.05 m/s")
    axes[0].legend()
    log_s, log_w = logs["grf_swbc_T1"], logs["grf_stance_T1"]
    for log, kind, color in ((log_s, "swbc", "C0"), (log_w, "stance", "C2")):
        window = (log.t >= 6.0) & (log.t <= 10.0)
        axes[1].plot(log.t[window], log.contact_force[window, LF, 2], color=color, label=f"{LABELS[kind]} actual")
        axes[1].plot(log.t[window], log.wbc_forces[window, LF, 2], color=color, ls="--",
                     label=f"{LABELS[kind]} optimal")
    axes[1].set_xlabel("t [s]")
    axes[1].set_ylabel("LF normal force [N]")
    axes[1].set_title("T1: actual vs optimal")
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "grf_tracking.png", dpi=110)
    plt.close(fig)
    return result


# -- 2. TCE accuracy -------------------------------------------------------------------------------------
def settled_mask(log: ClosedLoopLog, leg: int, window: int) -> np.ndarray:
    """Samples at which the leg's last ``window`` TCE stance samples all lie on the current terrain."""
    recent: deque[float] = deque(maxlen=window)
    out = np.zeros(len(log.t), dtype=bool)
    for i in range(len(log.t)):
        if log.tce_in_contact[i, leg]:
            recent.append(float(log.terrain_stiffness[i, leg]))
            out[i] = len(recent) == window and all(k == recent[-1] for k in recent)
    return out


def tce_accuracy(log: ClosedLoopLog, window: int) -> dict:
    """Per leg and terrain: mean, std and % error of the estimate over settled stance samples."""
    result: dict[str, dict] = {}
    for leg in LEGS:
        settled = settled_mask(log, int(leg), window) & np.isfinite(log.tce_stiffness[:, leg])
        per_terrain = {}
        for k_true, terrain in TERRAIN_BY_STIFFNESS.items():
            mask = settled & (log.terrain_stiffness[:, leg] == k_true)
            if mask.sum() < 10:
                continue
            values = log.tce_stiffness[mask, leg]
            per_terrain[terrain] = {"true_n_per_m": k_true, "mean_n_per_m": float(np.mean(values)),
                                    "std_n_per_m": float(np.std(values)),
                                    "error_percent": float(100.0 * abs(np.mean(values) - k_true) / k_true),
                                    "samples": int(mask.sum())}
        result[leg.name] = per_terrain
    return result


def plot_estimates(log: ClosedLoopLog, path: Path, title: str) -> None:
    """Per leg: the TCE estimate over time against the true stiffness under the foot (log scale)."""
    fig, axes = plt.subplots(4, 1, figsize=(11, 10), sharex=True)
    for leg, ax in zip(LEGS, axes):
        ax.semilogy(log.t, log.terrain_stiffness[:, leg], "k--", lw=1.2, label="true")
        ax.semilogy(log.t, log.tce_stiffness[:, leg], color="C3", lw=1.0, label="TCE estimate")
        ax.set_ylabel(f"{leg.name} k [N/m]")
        ax.set_ylim(1e3, 1e7)
    axes[0].legend(loc="upper right")
    axes[0].set_title(title)
    axes[-1].set_xlabel("t [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# -- 3. aggressive manoeuvres ------------------------------------------------------------------------------
def contact_losses(log: ClosedLoopLog) -> dict[str, object]:
    """Transitions of a planned stance foot from true contact to no contact, per leg."""
    lost = log.stance[1:] & log.foot_contact[:-1] & ~log.foot_contact[1:]
    losses = lost.sum(axis=0)
    return {"per_leg": {leg.name: int(losses[leg]) for leg in LEGS}, "total": int(losses.sum()),
            "time_without_contact_s": float(np.sum(log.stance & ~log.foot_contact) * log.dt),
            "fell": log.fell, "fall_time_s": log.meta.get("fall_time_s"), "sim_time_s": float(log.t[-1] + log.dt)}


def aggressive_analysis(logs: dict[str, ClosedLoopLog], out: Path) -> dict:
    result = {kind: contact_losses(logs[f"aggressive_{kind}"]) for kind in ("swbc", "stance")}
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    for kind, color in (("swbc", "C0"), ("stance", "C2")):
        log = logs[f"aggressive_{kind}"]
        axes[0].plot(log.t, 1e3 * log.foot_position[:, LF, 2], color=color, label=LABELS[kind])
        axes[1].plot(log.t, np.degrees(log.base_rpy[:, 0]), color=color, label=f"{LABELS[kind]} actual")
        axes[2].plot(log.t, np.sum(log.foot_contact, axis=1) + (0.05 if kind == "stance" else 0.0), color=color)
    log = logs["aggressive_stance"]
    axes[1].plot(log.t, np.degrees(log.rpy_des[:, 0]), "k--", lw=0.8, label="desired")
    axes[0].set_ylabel("LF foot z [mm]")
    axes[1].set_ylabel("roll [deg]")
    axes[2].set_ylabel("feet in contact")
    axes[2].set_xlabel("t [s]")
    axes[0].legend()
    axes[1].legend(fontsize=8)
    axes[0].set_title("Aggressive trunk manoeuvres on T1 (0.05 m at 1.8 Hz, 0.5 rad at 1.5 Hz)")
    fig.tight_layout()
    fig.savefig(out / "aggressive.png", dpi=110)
    plt.close(fig)
    return result


# -- 4. speed ramp -------------------------------------------------------------------------------------------
def ramp_analysis(logs: dict[str, ClosedLoopLog], out: Path) -> dict:
    result = {}
    fig, axes = plt.subplots(3, 1, figsize=(11, 9), sharex=True)
    for kind, color in (("swbc", "C0"), ("stance", "C2")):
        log = logs[f"ramp_{kind}"]
        end = log.t[-1]
        result[kind] = {"fell": log.fell, "fall_time_s": log.meta.get("fall_time_s"),
                        "commanded_speed_at_end_m_s": float(log.cmd_profile[-1, 0]),
                        "reference_speed_at_end_m_s": float(log.cmd_velocity_h[-1, 0]),
                        "mean_speed_last_2s_m_s": float(np.mean(log.velocity_h[log.t >= end - 2.0, 0])),
                        "distance_m": float(log.base_position[-1, 0] - log.base_position[0, 0]),
                        "completed": not log.fell and end + log.dt >= float(log.meta["duration_s"]) - 1e-6}
        axes[0].plot(log.t, log.velocity_h[:, 0], color=color, lw=0.6, alpha=0.7, label=f"{LABELS[kind]} actual")
        axes[0].plot(log.t, log.cmd_velocity_h[:, 0], color=color, ls="--", label=f"{LABELS[kind]} reference")
        axes[1].plot(log.t, 1e3 * log.foot_position[:, 1, 2], color=color, lw=0.7, label=LABELS[kind])
        axes[2].plot(log.t, 1e3 * log.penetration[:, 1], color=color, lw=0.7, label=f"{LABELS[kind]} actual")
        if kind == "stance":
            axes[2].plot(log.t, 1e3 * log.penetration_des[:, 1], "k--", lw=0.6, label="STANCE desired")
        if log.fell:
            axes[0].axvline(float(log.meta["fall_time_s"]), color=color, ls=":")
    axes[0].set_ylabel("forward speed [m/s]")
    axes[1].set_ylabel("RF foot z [mm]")
    axes[2].set_ylabel("RF penetration [mm]")
    axes[2].set_xlabel("t [s]")
    for ax in axes:
        ax.legend(fontsize=7, loc="upper left")
    axes[0].set_title("Speed ramp on T1, crawl 0.05 -> 0.3 m/s at 0.005 m/s^2")
    fig.tight_layout()
    fig.savefig(out / "speed_ramp.png", dpi=110)
    plt.close(fig)
    return result


# -- 5. energy -------------------------------------------------------------------------------------------------
def energy_analysis(logs: dict[str, ClosedLoopLog], out: Path) -> dict:
    result: dict[str, dict] = {}
    for speed in ENERGY_SPEEDS:
        entry = {}
        for kind in ("swbc", "stance"):
            log = logs[f"energy_{kind}_{speed:g}"]
            mask = log.after(SETTLE_S)
            energy = float(np.sum(log.power[mask]) * log.dt)
            distance = float(log.base_position[mask][-1, 0] - log.base_position[mask][0, 0])
            entry[kind] = {"energy_j": energy, "distance_m": distance, "energy_per_m_j": energy / max(distance, 1e-6),
                           "mean_power_w": float(np.mean(log.power[mask])), "fell": log.fell,
                           "window_s": float(mask.sum() * log.dt)}
        entry["stance_minus_swbc_percent"] = 100.0 * (entry["stance"]["energy_j"] - entry["swbc"]["energy_j"]) / \
            entry["swbc"]["energy_j"]
        result[f"{speed:g}"] = entry
    fig, ax = plt.subplots(figsize=(7, 4))
    width = 0.35
    for i, kind in enumerate(("swbc", "stance")):
        ax.bar(np.arange(len(ENERGY_SPEEDS)) + (i - 0.5) * width,
               [result[f"{s:g}"][kind]["mean_power_w"] for s in ENERGY_SPEEDS], width, label=LABELS[kind])
    ax.set_xticks(range(len(ENERGY_SPEEDS)), [f"{s:g} m/s" for s in ENERGY_SPEEDS])
    ax.set_ylabel("mean mechanical power sum|tau qd| [W]")
    ax.set_title("Crawl on T1")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "energy.png", dpi=110)
    plt.close(fig)
    return result


# -- report --------------------------------------------------------------------------------------------------
def markdown(grf: dict, tce: dict, lateral: dict, aggressive: dict, ramp: dict, energy: dict) -> str:
    rows = [[t] + [grf[t][k]["mae_n"] for k in CONTROLLERS] + [LABELS[grf[t]["best"]]]
            + [f"{grf[t][k]['bias_n']:+.2f} / {grf[t][k]['std_n']:.2f}" for k in CONTROLLERS]
            for t in ("T1", "T2", "T4")]
    text = ["# STANCE experiments (crawl; ground-truth base state for the TCE, as the thesis' motion capture)\n",
            "## 1. GRF tracking: LF normal force MAE [N], 0.05 m/s\n",
            _table(["terrain"] + [LABELS[k] for k in CONTROLLERS] + ["best"]
                   + [f"{LABELS[k]} bias / std" for k in CONTROLLERS], rows), "\n",
            "## 2. TCE accuracy, transition course rigid -> T1 -> T2 -> T3 -> rigid (0.1 m/s)\n",
            "Samples whose whole 250-sample window lies on the terrain.\n"]
    tce_rows = []
    for leg, per_terrain in tce.items():
        for terrain, r in per_terrain.items():
            tce_rows.append([leg, terrain, r["true_n_per_m"], r["mean_n_per_m"], r["std_n_per_m"],
                             f"{r['error_percent']:.2f}", THESIS_TCE_ERROR[terrain]])
    text.append(_table(["leg", "terrain", "true [N/m]", "mean [N/m]", "std [N/m]", "error [%]",
                        "thesis LF error [%]"], tce_rows))
    text.append("\n\n## 3. Lateral transition (left feet on T1, right feet rigid), final estimates\n")
    text.append(_table(["leg", "terrain", "estimate [N/m]", "error [%]"],
                       [[leg, r["terrain"], r["estimate_n_per_m"], f"{r['error_percent']:.2f}"]
                        for leg, r in lateral.items()]))
    text.append("\n\n## 4. Aggressive trunk manoeuvres on T1\n")
    text.append(_table(["controller", "contact losses", "per leg", "time w/o contact [s]", "fell", "fall t [s]"],
                       [[LABELS[k], r["total"], r["per_leg"], r["time_without_contact_s"], r["fell"],
                         r["fall_time_s"]] for k, r in aggressive.items()]))
    text.append("\n\n## 5. Speed ramp on T1 (0.05 -> 0.3 m/s)\n")
    text.append(_table(["controller", "completed", "fell", "fall t [s]", "reference speed at end [m/s]",
                        "distance [m]"],
                       [[LABELS[k], r["completed"], r["fell"], r["fall_time_s"], r["reference_speed_at_end_m_s"],
                         r["distance_m"]] for k, r in ramp.items()]))
    text.append("\n\n## 6. Energy on T1\n")
    text.append(_table(["speed [m/s]", "sWBC energy [J]", "STANCE energy [J]", "STANCE - sWBC [%]",
                        "sWBC [J/m]", "STANCE [J/m]"],
                       [[s, e["swbc"]["energy_j"], e["stance"]["energy_j"], f"{e['stance_minus_swbc_percent']:+.1f}",
                         e["swbc"]["energy_per_m_j"], e["stance"]["energy_per_m_j"]] for s, e in energy.items()]))
    return "\n".join(text) + "\n"


def lateral_analysis(log: ClosedLoopLog, out: Path) -> dict:
    result = {}
    for leg in LEGS:
        k_true = float(log.terrain_stiffness[-1, leg])
        k_est = float(log.tce_stiffness[-1, leg])
        result[leg.name] = {"terrain": TERRAIN_BY_STIFFNESS.get(k_true, "?"), "true_n_per_m": k_true,
                            "estimate_n_per_m": k_est, "error_percent": 100.0 * abs(k_est - k_true) / k_true}
    plot_estimates(log, out / "lateral_transition.png", "Lateral transition: left feet on T1, right feet rigid")
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="short runs for a smoke check")
    parser.add_argument("--out", type=Path, default=Path("results/stance"))
    parser.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1))
    args = parser.parse_args(argv)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    runs = plan(out, args.quick)
    logs = execute(runs, max(1, args.jobs))
    grf = grf_analysis(logs, out)
    tce = tce_accuracy(logs["tce_transition"], TceSettings().window)
    plot_estimates(logs["tce_transition"], out / "tce_transition.png",
                   "TCE on the transition course (rigid, T1, T2, T3, rigid), STANCE crawl 0.1 m/s")
    lateral = lateral_analysis(logs["lateral"], out)
    aggressive = aggressive_analysis(logs, out)
    ramp = ramp_analysis(logs, out)
    energy = energy_analysis(logs, out)
    report = markdown(grf, tce, lateral, aggressive, ramp, energy)
    (out / "summary.md").write_text(report)
    wall = time.perf_counter() - start
    sim = sum(float(log.t[-1] + log.dt) for log in logs.values())
    (out / "summary.json").write_text(json.dumps(_finite({
        "grf_tracking": grf, "tce_transition": tce, "lateral": lateral, "aggressive": aggressive,
        "speed_ramp": ramp, "energy": energy,
        "run": {"quick": args.quick, "wall_time_s": wall, "simulated_s": sim,
                "per_run_wall_s": {k: float(v.meta["wall_time_s"]) for k, v in logs.items()}}}), indent=2))
    sys.stderr.write(f"done: {len(logs)} runs, {sim:.0f} s simulated in {wall:.0f} s wall -> {out}\n")
    print(report)
    return 0


if __name__ == "__main__":
    sys.exit(main())

