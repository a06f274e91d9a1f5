"""Markdown report with PNG plots of one identification: residuals before/after per channel on the
held-out data, an overlaid held-out segment, the named effects with intervals, every candidate's outcome."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .identify import Identification  # noqa: E402
from .library import CANDIDATES_BY_NAME  # noqa: E402


def _fmt(value: float) -> str:
    if not math.isfinite(value):
        return "inf"
    return f"{value:.4g}"


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_channels(result: Identification, path: Path) -> Path:
    """Bar chart: held-out RMS error per channel before and after adding the named effects."""
    names, before, after = [], [], []
    for sub in result.subsystems.values():
        for channel, value in sub.channels_before.items():
            names.append(f"{sub.name}\n{channel}")
            before.append(value)
            after.append(sub.channels_after.get(channel, math.nan))
    fig, ax = plt.subplots(figsize=(max(6.0, 0.9 * len(names)), 4.0))
    x = np.arange(len(names))
    ax.bar(x - 0.2, before, 0.4, label="nominal model")
    ax.bar(x + 0.2, after, 0.4, label="updated model")
    ax.set_xticks(x, names, rotation=60, ha="right", fontsize=7)
    ax.set_yscale("log")
    ax.set_ylabel("held-out RMS error (channel units)")
    ax.set_title(f"Sim-vs-measured gap per channel: {Path(result.bag).name}")
    ax.legend()
    return _save(fig, path)


def plot_overlay(overlay: dict[str, np.ndarray], path: Path) -> Path:
    """Held-out open-loop segments: a joint velocity and the base height, measured vs predicted."""
    fig, axes = plt.subplots(2, 1, figsize=(8.0, 5.0), sharex=True)
    t = overlay["t_s"]
    for key, style in (("measured", "k-"), ("nominal", "C0--"), ("updated", "C1-")):
        axes[0].plot(t, overlay[f"{key}_qd"], style, label=key, lw=1.0)
        axes[1].plot(t, overlay[f"{key}_z"], style, label=key, lw=1.0)
    axes[0].set_ylabel(f"{overlay['joint']} velocity [rad/s]")
    axes[1].set_ylabel("base height [m]")
    axes[1].set_xlabel("time [s] (segments restart from the measured state every 0.1 s)")
    axes[0].legend(fontsize=8)
    return _save(fig, path)


def plot_closed_loop(closed: dict[str, np.ndarray], path: Path) -> Path:
    """Closed-loop re-run with the same controller and commands: base x, y and height."""
    fig, axes = plt.subplots(3, 1, figsize=(8.0, 6.0), sharex=True)
    for key, style in (("measured", "k-"), ("nominal", "C0--"), ("updated", "C1-")):
        if f"{key}_pos" not in closed:
            continue
        for i, label in enumerate(("x [m]", "y [m]", "z [m]")):
            axes[i].plot(closed[f"{key}_t"], closed[f"{key}_pos"][:, i], style, label=key, lw=1.0)
            axes[i].set_ylabel(f"base {label}")
    axes[0].legend(fontsize=8)
    axes[2].set_xlabel("time [s]")
    return _save(fig, path)


def write_report(
    result: Identification,
    out_dir: Path,
    overlay: dict[str, np.ndarray] | None = None,
    closed: dict[str, np.ndarray] | None = None,
    model_path: Path | None = None,
) -> Path:
    """Write ``report.md`` and its PNGs into ``out_dir``; returns the report path."""
    out_dir.mkdir(parents=True, exist_ok=True)
    lines = [f"# Sim-vs-measured gap: {Path(result.bag).name}", ""]
    before, after = result.gap(False), result.gap(True)
    reduction = 1.0 - after / before if before > 0 else 0.0
    lines += [
        f"Bag `{result.bag}`; identification window {result.windows_s['identification'][0]:.2f}-"
        f"{result.windows_s['identification'][1]:.2f} s, held-out {result.windows_s['holdout'][0]:.2f}-"
        f"{result.windows_s['holdout'][1]:.2f} s; {result.elapsed_s:.1f} s, {result.simulated_steps} "
        "simulated steps.",
        "",
        f"**Held-out gap** (sum over subsystems of cost / noise floor; 1 per subsystem at the floor): "
        f"{before:.3g} -> {after:.3g} ({100 * reduction:.1f}% reduction).",
        "",
    ]
    named = result.named
    if named:
        lines += ["## Named effects", "", "| effect | parameter | value | 95% interval |", "|---|---|---|---|"]
        for f in named:
            for k, v in f.values.items():
                lo, hi = f.intervals.get(k, (math.nan, math.nan))
                lines.append(f"| {f.candidate} | {k} | {_fmt(v)} | [{_fmt(lo)}, {_fmt(hi)}] |")
        lines.append("")
    else:
        lines += ["## Named effects", "", "None: no missing effect found.", ""]
    lines += [
        "## Subsystems",
        "",
        "| subsystem | verdict | noise floor | nominal | fitted | held-out before | held-out after |",
        "|---|---|---|---|---|---|---|",
    ]
    for s in result.subsystems.values():
        lines.append(
            f"| {s.name} | {s.verdict} | {_fmt(s.floor)} | {_fmt(s.nominal_cost)} | {_fmt(s.fitted_cost)} | "
            f"{_fmt(s.holdout_before)} | {_fmt(s.holdout_after)} |"
        )
    lines += [
        "",
        "## Every candidate",
        "",
        "| candidate | subsystem | outcome | fitted/nominal cost | note |",
        "|---|---|---|---|---|",
    ]
    for f in result.findings:
        ratio = "" if f.cost_ratio is None else f"{f.cost_ratio:.3g}"
        lines.append(
            f"| {f.candidate} ({CANDIDATES_BY_NAME[f.candidate].description}) | {f.subsystem} | {f.status} | "
            f"{ratio} | {f.note} |"
        )
    if result.rejected_samples:
        lines += ["", f"Rejected samples (out-of-order, repeated stamps or non-finite): {result.rejected_samples}"]
    lines += ["", "## Plots", "", f"![gap per channel]({plot_channels(result, out_dir / 'gap_channels.png').name})"]
    if overlay is not None:
        lines.append(f"![held-out segments]({plot_overlay(overlay, out_dir / 'holdout_overlay.png').name})")
    if closed is not None:
        lines.append(f"![closed loop]({plot_closed_loop(closed, out_dir / 'closed_loop.png').name})")
        for key in ("nominal", "updated"):
            if f"{key}_rms_m" in closed:
                lines.append(
                    f"- closed-loop re-run, {key} model: base position RMS error {float(closed[f'{key}_rms_m']):.4f} m"
                )
    if model_path is not None:
        lines += ["", f"Updated model configuration: `{model_path}`"]
    path = out_dir / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path
