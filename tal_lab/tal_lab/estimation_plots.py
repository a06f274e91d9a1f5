"""Thesis-like figures of the soft-terrain state-estimation study (``estimation_experiments``).

``plot_all`` writes into ``out`` (times are simulation times [s]):

* ``specific_force_z.png``: IMU z specific force (base frame) per surface in the zoom window, each leg's
  stance from the rigid estimator's contact flags as strips;
* ``grf_z.png``: the rigid estimator's z GRF per leg and surface in the zoom window, true stance shaded,
  with the rigid estimator's contact threshold;
* ``position_<surface>.png``, ``velocity_<surface>.png``: estimates vs ground truth over the run (velocity
  also in the zoom window, with the raw leg odometry).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

from tal_core.legs import LEGS  # noqa: E402
from tal_core.robot_model import RobotModel  # noqa: E402
from tal_estimation.leg_odometry import LegOdometry  # noqa: E402
from tal_lab.estimation_experiments import ZOOM_S  # noqa: E402
from tal_lab.offline_estimation import EstimateArrays  # noqa: E402

if TYPE_CHECKING:
    from tal_lab.estimation_experiments import Recording

Estimates = dict[tuple[str, str], EstimateArrays]
Span = tuple[float, float]
SURFACE_COLOURS = {"rigid": "C0", "soft": "C3"}
LEG_COLOURS = ("C1", "C2", "C4", "C5")
AXES = ("x", "y", "z")
TRUTH = {"color": "k", "lw": 1.0, "label": "ground truth"}
VARIANT_STYLE = {
    "rigid": {"color": "C0", "lw": 1.0, "label": "rigid estimator"},
    "terrain_aware_tce": {"color": "C2", "lw": 1.0, "label": "terrain-aware estimator (TCE)"},
}
RAW_LEG_ODOMETRY = {"color": "C7", "lw": 0.5, "alpha": 0.7, "label": "raw leg odometry (rigid)"}
DPI = 110


@lru_cache(maxsize=1)
def contact_threshold_n(robot: str = "hyq") -> float:
    """The rigid leg odometry's contact threshold on |F| [N] (default settings; the model is built once)."""
    return float(LegOdometry(RobotModel.from_name(robot)).threshold_n)


def zoom_window(t: np.ndarray, window: tuple[float, float] = ZOOM_S) -> tuple[float, float]:
    """``window`` [s], shifted back (and shortened if needed) to lie within the samples ``t``."""
    length = window[1] - window[0]
    end = min(window[1], float(t[-1]))
    return max(float(t[0]), end - length), end


def _mask(t: np.ndarray, window: tuple[float, float]) -> np.ndarray:
    return (t >= window[0] - 1e-9) & (t <= window[1] + 1e-9)


def _segments(t: np.ndarray, flags: np.ndarray) -> list[tuple[float, float]]:
    """(start, end) [s] of the runs of True in ``flags``; a sample covers one sample period."""
    if len(t) == 0:
        return []
    period = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    edges = np.diff(np.r_[0, flags.astype(int), 0])
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [(float(t[s]), float(t[e - 1]) + period) for s, e in zip(starts, ends)]


def _shade(
    ax: plt.Axes, t: np.ndarray, on: np.ndarray, colour: str, span: Span = (0.0, 1.0), alpha: float = 0.2
) -> None:
    """Shade the runs of True in ``on`` over ``span`` (fractions of the axes' height)."""
    for start, end in _segments(t, on):
        ax.axvspan(start, end, ymin=span[0], ymax=span[1], color=colour, alpha=alpha, lw=0)


def _save(fig: plt.Figure, path: Path, bottom: float = 0.0) -> Path:
    fig.tight_layout(rect=(0.0, bottom, 1.0, 1.0))
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def plot_specific_force(recordings: dict[str, Recording], estimates: Estimates, out: Path) -> Path:
    """z specific force per surface in the zoom window, stance strips from the rigid estimator's flags."""
    fig, axes = plt.subplots(len(recordings), 1, figsize=(10, 3.2 * len(recordings)), squeeze=False, sharey=True)
    for ax, (surface, rec) in zip(axes[:, 0], recordings.items()):
        t, f = rec.sensors.t, rec.sensors.specific_force[:, 2]
        window = zoom_window(t)
        m = _mask(t, window)
        ax.plot(t[m], f[m], color=SURFACE_COLOURS.get(surface, "C7"), lw=0.8, label="specific force z (1 kHz)")
        est = estimates[(surface, "rigid")]
        e = _mask(est.t, window)
        for leg in LEGS:  # one strip per leg at the top of the axes
            _shade(ax, est.t[e], est.contact[e, leg], LEG_COLOURS[leg], (0.92 - 0.05 * leg, 0.97 - 0.05 * leg), 0.6)
        ax.set_xlim(window)
        ax.set_title(f"{surface} ground: z specific force (base frame); strips: stance, rigid estimator flags")
        ax.set_ylabel("f_z [m/s^2]")
        handles = ax.get_legend_handles_labels()[0] + [
            Patch(color=LEG_COLOURS[leg], alpha=0.6, label=f"{leg.name} stance") for leg in LEGS
        ]
        ax.legend(handles=handles, fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        ax.margins(y=0.35)
    axes[-1, 0].set_xlabel("t [s]")
    return _save(fig, out / "specific_force_z.png")


def plot_grf(recordings: dict[str, Recording], estimates: Estimates, out: Path) -> Path:
    """The rigid estimator's z GRF per leg (rows) and surface (columns), true stance shaded."""
    threshold = contact_threshold_n()
    surfaces = list(recordings)
    fig, axes = plt.subplots(
        len(LEGS), len(surfaces), figsize=(6 * len(surfaces), 9), squeeze=False, sharey=True, sharex="col"
    )
    for col, surface in enumerate(surfaces):
        log, est = recordings[surface].log, estimates[(surface, "rigid")]
        colour = SURFACE_COLOURS.get(surface, "C7")
        window = zoom_window(est.t)
        m, e = _mask(log.t, window), _mask(est.t, window)
        for leg in LEGS:
            ax = axes[leg, col]
            _shade(ax, log.t[m], log.foot_contact[m, leg], "0.5")
            ax.plot(log.t[m], log.contact_force[m, leg, 2], "k--", lw=0.7, label="true F_z (simulator)")
            ax.plot(est.t[e], est.force[e, leg, 2], color=colour, lw=1.0, label="estimated F_z (rigid estimator)")
            ax.axhline(threshold, color="C1", lw=0.8, ls=":", label=f"contact threshold on |F| ({threshold:.0f} N)")
            ax.set_xlim(window)
            ax.set_ylabel(f"{leg.name} F_z [N]")
            if leg == LEGS[0]:
                ax.set_title(f"{surface} ground: z ground reaction force (shaded: true stance)")
        axes[-1, col].set_xlabel("t [s]")
    handles = axes[0, 0].get_legend_handles_labels()[0]
    stance = Patch(color="0.5", alpha=0.2, label="true stance (simulator contact)")
    fig.legend(handles=[*handles, stance], loc="lower center", ncol=4, fontsize=8)
    return _save(fig, out / "grf_z.png", bottom=0.04)


def _truth_at(t_truth: np.ndarray, values: np.ndarray, t: float) -> np.ndarray:
    """The ground-truth row at (or just before) time ``t`` [s]."""
    return values[max(0, int(np.searchsorted(t_truth, t + 1e-9)) - 1)]


def plot_position(surface: str, rec: Recording, estimates: Estimates, out: Path) -> Path:
    """Estimated vs true position (x, y, z) over the run, each relative to its value at the first tick."""
    t = rec.sensors.t
    start = float(estimates[(surface, "rigid")].t[0])
    truth = rec.true_position - _truth_at(t, rec.true_position, start)
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    for k, ax in enumerate(axes):
        ax.plot(t, 1e3 * truth[:, k], **TRUTH)
        for variant, style in VARIANT_STYLE.items():
            if (surface, variant) in estimates:
                est = estimates[(surface, variant)]
                ax.plot(est.t, 1e3 * (est.position[:, k] - est.position[0, k]), **style)
        ax.set_ylabel(f"{AXES[k]} - {AXES[k]}(0) [mm]")
    axes[0].set_title(f"{surface} ground: base position, estimated vs ground truth (relative to the start)")
    axes[0].legend(fontsize=8)
    axes[-1].set_xlabel("t [s]")
    return _save(fig, out / f"position_{surface}.png")


def plot_velocity(surface: str, rec: Recording, estimates: Estimates, out: Path) -> Path:
    """Velocity x, y, z (columns) over the run (top) and in the zoom window (bottom)."""
    t = rec.sensors.t
    raw = estimates[(surface, "rigid")]
    window = zoom_window(raw.t)
    fig, axes = plt.subplots(2, 3, figsize=(15, 7))
    for row, mask_of in enumerate((lambda x: np.ones(len(x), bool), lambda x: _mask(x, window))):
        for k in range(3):
            ax = axes[row, k]
            m, r = mask_of(t), mask_of(raw.t)
            shown = [rec.true_velocity[m, k], np.nanpercentile(raw.leg_odometry_velocity[r, k], [1.0, 99.0])]
            ax.plot(t[m], rec.true_velocity[m, k], zorder=3, **TRUTH)
            ax.plot(raw.t[r], raw.leg_odometry_velocity[r, k], **RAW_LEG_ODOMETRY)
            for variant, style in VARIANT_STYLE.items():
                if (surface, variant) in estimates:
                    est = estimates[(surface, variant)]
                    e = mask_of(est.t)
                    ax.plot(est.t[e], est.linear_velocity[e, k], **style)
                    shown.append(est.linear_velocity[e, k])
            low, high = np.nanmin(np.concatenate(shown)), np.nanmax(np.concatenate(shown))
            ax.set_ylim(low - 0.1 * (high - low) - 1e-3, high + 0.1 * (high - low) + 1e-3)
            ax.set_title(f"v_{AXES[k]}, {'full run' if row == 0 else f'zoom {window[0]:.0f}-{window[1]:.0f} s'}")
            ax.set_xlabel("t [s]")
            ax.set_ylabel(f"v_{AXES[k]} [m/s] (world)")
            if row == 1:
                ax.set_xlim(window)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"{surface} ground: base velocity (world frame); y range omits raw leg odometry's outer 2 %")
    return _save(fig, out / f"velocity_{surface}.png")


def plot_all(recordings: dict[str, Recording], estimates: Estimates, out: Path) -> list[Path]:
    """Write every figure of the study into ``out``; returns the PNG paths.

    recordings: surface -> Recording; estimates: (surface, variant) -> EstimateArrays, variants ``rigid``
    (required) and ``terrain_aware_tce`` (drawn when present).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = [plot_specific_force(recordings, estimates, out), plot_grf(recordings, estimates, out)]
    for surface, rec in recordings.items():
        paths.append(plot_position(surface, rec, estimates, out))
        paths.append(plot_velocity(surface, rec, estimates, out))
    return paths
