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
from .library import CANDIDATES_BY_NAME, VARIANTS_BY_NAME  # noqa: E402


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


def plot_remainder(result: Identification, path: Path) -> Path | None:
    """Per subsystem with a remainder: held-out cost / noise floor (re-estimated with the updated model) per
    channel, joint, leg and gait phase; the dashed line is the remainder threshold."""
    from .remainder import REMAINDER_FACTOR

    remainders = result.remainders
    if not remainders:
        return None
    tables = ("channel", "joint", "leg", "phase")
    fig, axes = plt.subplots(len(remainders), len(tables), figsize=(14.0, 3.2 * len(remainders)), squeeze=False)
    for row, (name, rem) in enumerate(remainders.items()):
        for col, table in enumerate(tables):
            ax = axes[row, col]
            groups = getattr(rem, f"by_{table}")
            labels = list(groups)
            ratios = [max(groups[k].ratio, 1e-3) for k in labels]
            top = rem.top(table) if rem.flagged else ""
            colors = ["C3" if k == top else "C0" for k in labels]
            ax.bar(np.arange(len(labels)), ratios, color=colors)
            ax.set_xticks(np.arange(len(labels)), [k.replace("_joint", "") for k in labels], rotation=60, fontsize=7)
            ax.set_yscale("log")
            ax.axhline(1.0, color="k", lw=0.8)
            ax.axhline(REMAINDER_FACTOR, color="k", lw=0.8, ls="--")
            ax.set_title(f"{name}: per {table}", fontsize=9)
            if col == 0:
                ax.set_ylabel("held-out cost / noise floor")
    fig.suptitle(f"What the updated model leaves: {Path(result.bag).name} ({result.verdict[:90]})", fontsize=9)
    return _save(fig, path)


def _remainder_lines(result: Identification) -> list[str]:
    from .remainder import ISOLATED_SEGMENTS, MOSTLY_EXPLAINED, REMAINDER_FACTOR

    remainders = result.remainders
    if not remainders:
        return []
    lines = [
        "## What remains, and where",
        "",
        f"Held-out cost of the updated model against the noise floor re-estimated with it (1 = at the floor). "
        f'Above {REMAINDER_FACTOR:g} floors a remainder is reported: "partly explained" when the named effects '
        f'remove at least {100 * MOSTLY_EXPLAINED:.0f}% of the held-out excess, otherwise "not explained by the '
        "library\". Share: the group's part of the excess over the floor (where to look). The dynamics' "
        f"verdict and tables leave out its worst {100 * ISOLATED_SEGMENTS:.0f}% of held-out open-loop segments, "
        "listed below as isolated events (a contact transition a re-simulated segment resolves differently).",
        "",
        "| subsystem | held-out before | after | floor (updated model) | after / floor | without isolated segments "
        "| verdict |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, r in remainders.items():
        kept = f"{r.systematic_ratio:.3g} ({len(r.isolated)} set aside)" if r.isolated else "-"
        lines.append(
            f"| {name} | {_fmt(r.before)} | {_fmt(r.after)} | {_fmt(r.floor)} | {r.ratio:.3g} | {kept} | {r.verdict} |"
        )
    for name, r in remainders.items():
        if not r.isolated:
            continue
        lines += [
            "",
            f"{name}, isolated segments:",
            "",
            "| start [s] | cost / floor | share of the excess | joint |",
            "|---|---|---|---|",
        ]
        lines += [f"| {e.start_s:.2f} | {e.ratio:.3g} | {100 * e.share:.0f}% | {e.joint} |" for e in r.isolated]
    for name, r in remainders.items():
        for table in ("channel", "joint", "leg", "phase"):
            groups = getattr(r, f"by_{table}")
            if not groups or (table == "channel" and len(groups) == 1):
                continue
            lines += [
                "",
                f"{name}, per {table}:",
                "",
                f"| {table} | cost / floor | share of the excess |",
                "|---|---|---|",
            ]
            for key, g in groups.items():
                mark = " **(largest)**" if r.flagged and key == r.top(table) else ""
                lines.append(f"| {key}{mark} | {g.ratio:.3g} | {100 * g.share:.0f}% |")
    lines.append("")
    return lines


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
        f"**Verdict**: {result.verdict}.",
        "",
    ]
    named = result.named
    if named:
        lines += ["## Named effects", "", "| effect | parameter | value | 95% interval |", "|---|---|---|---|"]
        for f in named:
            for k, v in f.values.items():
                lo, hi = f.intervals.get(k, (math.nan, math.nan))
                lines.append(f"| {f.label} | {k} | {_fmt(v)} | [{_fmt(lo)}, {_fmt(hi)}] |")
        lines.append("")
        if any(f.where for f in named):
            lines += [
                "Per-leg and per-joint effects (`leg_*`, `encoder_offset`) are not sim_bridge parameters (its effects "
                "are global): they are left out of `model_updated.yaml`; a sensor effect (torque-sensor gain, encoder "
                "offset) is a calibration of the recording, not of the simulator.",
                "",
            ]
    else:
        lines += ["## Named effects", "", "None: no missing effect found.", ""]
    lines += [
        "## Subsystems",
        "",
        "| subsystem | verdict | noise floor (nominal model) | floor (chosen model) | nominal | fitted | "
        "held-out before | held-out after | held-out floor (updated model) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for s in result.subsystems.values():
        lines.append(
            f"| {s.name} | {s.verdict} | {_fmt(s.floor)} | {_fmt(s.floor_updated)} | {_fmt(s.nominal_cost)} | "
            f"{_fmt(s.fitted_cost)} | {_fmt(s.holdout_before)} | {_fmt(s.holdout_after)} | {_fmt(s.holdout_floor)} |"
        )
    lines += [""] + _remainder_lines(result)
    lines += [
        "",
        "## Every candidate",
        "",
        "| candidate | subsystem | outcome | fitted/nominal cost | note |",
        "|---|---|---|---|---|",
    ]
    for f in result.findings:
        ratio = "" if f.cost_ratio is None else f"{f.cost_ratio:.3g}"
        lines.append(f"| {f.label} ({_description(f.candidate)}) | {f.subsystem} | {f.status} | {ratio} | {f.note} |")
    if result.rejected_samples:
        lines += ["", f"Rejected samples (out-of-order, repeated stamps or non-finite): {result.rejected_samples}"]
    lines += ["", "## Plots", "", f"![gap per channel]({plot_channels(result, out_dir / 'gap_channels.png').name})"]
    remainder_png = plot_remainder(result, out_dir / "remainder.png")
    if remainder_png is not None:
        lines.append(f"![remainder per channel, joint, leg and gait phase]({remainder_png.name})")
    if overlay is not None:
        lines.append(f"![held-out segments]({plot_overlay(overlay, out_dir / 'holdout_overlay.png').name})")
    if closed is not None:
        lines.append(f"![closed loop]({plot_closed_loop(closed, out_dir / 'closed_loop.png').name})")
        for key in ("nominal", "updated"):
            if f"{key}_rms_m" in closed:
                lines.append(
                    f"- closed-loop re-run ({closed['gait'] if 'gait' in closed else 'trot'} gait, the recording's), "
                    f"{key} model: base position RMS error {float(closed[f'{key}_rms_m']):.4f} m"
                )
    if model_path is not None:
        lines += ["", f"Updated model configuration: `{model_path}`"]
    path = out_dir / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def _description(name: str) -> str:
    if name in CANDIDATES_BY_NAME:
        return CANDIDATES_BY_NAME[name].description
    return VARIANTS_BY_NAME[name].description
