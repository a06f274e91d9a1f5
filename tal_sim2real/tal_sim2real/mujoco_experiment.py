"""A second physics engine as the measured side (issue 34 item 5): ``python -m tal_sim2real mujoco``.

1. records an 8 s HyQ trot in MuJoCo (``tal_lab.mujoco_hyq``: the bridge's URDF, tal's sWBC on ground truth,
   the hidden-effect datasets' sensor noise) and the same trot in PyBullet (the model's own engine: the twin);
2. runs the gap workflow on the MuJoCo bag with the nominal PyBullet model (``identify_and_report``: the
   same steps as ``tal_sim2real identify BAG --course flat_rigid``), writing ``report.md`` and its PNGs;
3. as a control, identifies the PyBullet twin (the model against its own engine: it should name nothing);
4. writes ``README.md``: what was named, the held-out gap per channel before/after, where the remainder
   is, and the two engines side by side (distance, base height, stance sinkage and foot travel).

No labels exist for the MuJoCo data: whatever MuJoCo simulates is the truth.
"""

from __future__ import annotations

import logging
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tal_lab.mujoco_hyq import (
    COMMANDS,
    DURATION_S,
    JOINT_NOISE,
    MUJOCO_VERSION,
    MujocoModelError,
    MujocoRun,
    record_trot,
)

from tal_core.legs import LEG_NAMES
from tal_core.ros.bag_io import BagReader

from .errors import Sim2RealError
from .model import SimModel

LOG = logging.getLogger("tal.sim2real.mujoco")

SETTLE_S = 1.0  # [s] start-up excluded from the engine figures (as the workflow's settling window)
STANCE_FORCE_N = 20.0  # [N] a foot pushing less than this is not counted as a stance foot in the figures


@dataclass
class EngineFigures:
    """One engine's run, from its bag (after SETTLE_S): distance [m], base height [m], sinkage of the loaded
    stance feet [m], travel of a stance foot's sphere centre per stance [m] (rolling included)."""

    distance_m: float
    base_height_mean_m: float
    sinkage_mean_m: float
    sinkage_per_leg_m: dict[str, float]
    stance_travel_m: float
    t_s: np.ndarray
    base_xyz_m: np.ndarray


def engine_figures(bag: Path) -> EngineFigures:
    """Figures of a recorded run from its /ground_truth/odom and /ground_truth/contacts."""
    reader = BagReader(bag)
    t, xyz, ct, pen, loaded, feet = [], [], [], [], [], []
    for record in reader.messages(["/ground_truth/odom", "/ground_truth/contacts"]):
        m = record.message
        stamp = m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec
        if record.topic == "/ground_truth/odom":
            p = m.pose.pose.position
            t.append(stamp)
            xyz.append((p.x, p.y, p.z))
        else:
            ct.append(stamp)
            pen.append(list(m.penetration))
            loaded.append([bool(c) and f.z > STANCE_FORCE_N for c, f in zip(m.in_contact, m.force)])
            feet.append([(f.x, f.y) for f in m.foot_position])
    t_s, base = np.array(t), np.array(xyz)
    ct_s, pen_a, loaded_a, feet_a = np.array(ct), np.array(pen), np.array(loaded), np.array(feet)
    keep, keep_c = t_s >= SETTLE_S, ct_s >= SETTLE_S
    pen_a, loaded_a, feet_a = pen_a[keep_c], loaded_a[keep_c], feet_a[keep_c]
    both = loaded_a[1:] & loaded_a[:-1]
    travel = np.where(both, np.linalg.norm(np.diff(feet_a, axis=0), axis=2), 0.0).sum()
    stances = int(np.sum(loaded_a[1:] & ~loaded_a[:-1]))
    return EngineFigures(
        distance_m=float(np.linalg.norm(base[-1, :2] - base[0, :2])),
        base_height_mean_m=float(np.mean(base[keep, 2])),
        sinkage_mean_m=float(np.mean(pen_a[loaded_a])),
        sinkage_per_leg_m={leg: float(np.mean(pen_a[loaded_a[:, i], i])) for i, leg in enumerate(LEG_NAMES)},
        stance_travel_m=float(travel / max(stances, 1)),
        t_s=t_s,
        base_xyz_m=base,
    )


def record_twin(bag: Path, duration_s: float, seed: int) -> None:
    """The same trot in PyBullet (the nominal model's engine), recorded like the MuJoCo one."""
    from tal_lab.datasets import DatasetScenario, generate

    scenario = DatasetScenario(
        "pybullet_trot",
        "HyQ trot recorded in PyBullet, the twin of the MuJoCo trot (tal_sim2real)",
        "flat_rigid",
        commands=COMMANDS,
        joint_position_noise_std_rad=JOINT_NOISE[0],
        joint_velocity_noise_std_rad_s=JOINT_NOISE[1],
        joint_effort_noise_std_nm=JOINT_NOISE[2],
    )
    generate(scenario, bag, duration_s, seed=seed, progress=False)


def plot_engines(mj: EngineFigures, pb: EngineFigures, path: Path) -> Path:
    """Base x and height over time in both engines, and the stance sinkage per leg."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    for figures, label, style in ((mj, "MuJoCo (measured)", "-"), (pb, "PyBullet (model's engine)", "--")):
        axes[0].plot(figures.t_s, figures.base_xyz_m[:, 0], style, label=label, lw=1.0)
        axes[1].plot(figures.t_s, figures.base_xyz_m[:, 2], style, label=label, lw=1.0)
    axes[0].set(xlabel="time [s]", ylabel="base x [m]")
    axes[1].set(xlabel="time [s]", ylabel="base height [m]")
    axes[0].legend(fontsize=8)
    x = np.arange(len(LEG_NAMES))
    axes[2].bar(x - 0.2, [1e3 * mj.sinkage_per_leg_m[leg] for leg in LEG_NAMES], 0.4, label="MuJoCo")
    axes[2].bar(x + 0.2, [1e3 * pb.sinkage_per_leg_m[leg] for leg in LEG_NAMES], 0.4, label="PyBullet")
    axes[2].set_xticks(x, LEG_NAMES)
    axes[2].set(ylabel="mean stance sinkage [mm]")
    axes[2].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def run_mujoco_experiment(
    out: Path, data: Path, duration_s: float = DURATION_S, seed: int = 0, control: bool = True
) -> Path:
    """The whole comparison (module docstring); returns the README path."""
    from .cli import identify_and_report

    out, data = Path(out), Path(data)
    out.mkdir(parents=True, exist_ok=True)
    nominal = SimModel.nominal("flat_rigid")
    steps = 4 if control else 3
    sys.stderr.write(f"[mujoco] 1/{steps} recording the MuJoCo trot ({duration_s:g} s)\n")
    started = time.perf_counter()
    try:
        run = record_trot(data / "mujoco_trot", duration_s, seed=seed)
    except MujocoModelError as exc:
        raise Sim2RealError(str(exc)) from exc
    record_s = time.perf_counter() - started
    sys.stderr.write(f"[mujoco] 2/{steps} recording the PyBullet twin\n")
    record_twin(data / "pybullet_trot", duration_s, seed)
    sys.stderr.write(f"[mujoco] 3/{steps} identify the MuJoCo bag against the PyBullet model\n")
    started = time.perf_counter()
    result, report = identify_and_report(data / "mujoco_trot", nominal, out)
    identify_s = time.perf_counter() - started
    twin = None
    if control:
        sys.stderr.write(f"[mujoco] 4/{steps} control: identify the PyBullet twin\n")
        twin, _ = identify_and_report(data / "pybullet_trot", nominal, out / "control_pybullet", closed_loop=False)
    mj, pb = engine_figures(data / "mujoco_trot"), engine_figures(data / "pybullet_trot")
    plot_engines(mj, pb, out / "engines.png")
    readme = out / "README.md"
    readme.write_text(_readme(out, data, duration_s, seed, control, run, record_s, result, identify_s, twin, mj, pb))
    return readme


def _cut(before: float, after: float) -> str:
    return f"{100 * (1 - after / before):.2f} %" if before > 0 and math.isfinite(after) else "-"


def _readme(out, data, duration_s, seed, control, run: MujocoRun, record_s, result, identify_s, twin, mj, pb) -> str:
    command = f"python -m tal_sim2real mujoco --out {out} --data {data}"
    if duration_s != DURATION_S or seed:
        command += f" --duration-s {duration_s:g} --seed {seed}"
    if not control:
        command += " --no-control"
    before, after = result.gap(False), result.gap(True)
    lines = [
        "# A second physics engine as the measured side: HyQ trotting in MuJoCo",
        "",
        "```bash",
        f"{command}   # part of `make experiments`",
        "```",
        "",
        f"HyQ trots {duration_s:g} s at {COMMANDS[0][1]:g} m/s on flat ground in MuJoCo "
        f"(mujoco {MUJOCO_VERSION}), driven by tal's sWBC (rigid contact model, ground truth, 250 Hz; 1 kHz "
        "physics) and recorded with the hidden-effect datasets' topics and sensor noise. The gap workflow "
        "identifies it against the nominal PyBullet model (`--course flat_rigid`). No labels: what MuJoCo "
        "simulates is the truth. Model conversion: [mujoco_hyq.py](../../../tal_lab/tal_lab/mujoco_hyq.py); "
        "the workflow's full report: [report.md](report.md).",
        "",
        f"MuJoCo run: walked {run.net_displacement_m:.2f} m (PyBullet twin {pb.distance_m:.2f} m), base height "
        f"{run.base_height_mean_m:.3f} m mean, {run.base_height_min_m:.3f} m min (nominal "
        f"{run.nominal_base_height_m:.3f} m); model mass {run.total_mass_kg:.6f} kg; recorded in {record_s:.1f} s.",
        "",
        f"**Held-out gap** (sum over subsystems of cost / noise floor): {before:.3g} -> {after:.3g} "
        f"(cut {_cut(before, after)}); identification and report took {identify_s:.1f} s "
        f"({result.elapsed_s:.1f} s of it identification, the rest the closed-loop re-runs and plots).",
        "",
        f"**Verdict**: {result.verdict}.",
        "",
        "## Named",
        "",
    ]
    if result.named:
        lines += ["| effect | parameter | value | 95 % interval |", "|---|---|---|---|"]
        for f in result.named:
            for k, v in f.values.items():
                lo, hi = f.intervals.get(k, (math.nan, math.nan))
                lines.append(f"| {f.label} | {k} | {v:.4g} | [{lo:.4g}, {hi:.4g}] |")
    else:
        lines.append("Nothing.")
    lines += [
        "",
        "## Held-out gap per channel (RMS, channel units)",
        "",
        "| subsystem | channel | before | after | cut |",
        "|---|---|---|---|---|",
    ]
    for s in result.subsystems.values():
        for channel, b in s.channels_before.items():
            a = s.channels_after.get(channel, math.nan)
            lines.append(f"| {s.name} | {channel} | {b:.4g} | {a:.4g} | {_cut(b, a)} |")
    lines += ["", "## What remains, and where", ""]
    for name, r in result.remainders.items():
        lines.append(
            f"- {name}: held-out cost {r.after:.4g} against a floor of {r.floor:.4g} re-estimated with the "
            f"updated model ({r.ratio:.3g} x; {'a remainder' if r.flagged else 'no remainder'})."
        )
        if r.isolated:
            events = ", ".join(f"{e.start_s:.1f} s ({e.ratio:.3g} x, {e.joint})" for e in r.isolated)
            lines.append(
                f"  - without its {len(r.isolated)} isolated held-out segments ({events}, "
                f"{100 * sum(e.share for e in r.isolated):.0f} % of the excess): {r.systematic_ratio:.3g} x"
            )
        if r.systematic_ratio <= 1.0:
            continue
        lines.append("  - where the excess over the floor is" + ("" if r.flagged else " (below the threshold)") + ":")
        for table in ("channel", "joint", "leg", "phase"):
            groups = getattr(r, f"by_{table}")
            ranked = sorted(groups.items(), key=lambda kv: -kv[1].share)[:3]
            cells = ", ".join(f"{k} {100 * g.share:.0f} % ({g.ratio:.3g} x)" for k, g in ranked)
            lines.append(f"    - per {table}: {cells}")
    lines += [
        "",
        "Share: the group's part of the excess over the floor; (x): its cost / floor. Plot: "
        "[remainder.png](remainder.png).",
        "",
    ]
    lines += _engine_lines(run, mj, pb)
    if twin is not None:
        lines += [
            "",
            "## Control: the PyBullet twin against its own engine",
            "",
            f"The same trot recorded in PyBullet and identified the same way ([report](control_pybullet/"
            f"report.md)): held-out gap {twin.gap(False):.3g} -> {twin.gap(True):.3g}; verdict: "
            f"{twin.verdict}; named: {', '.join(f.label for f in twin.named) or 'nothing'}.",
        ]
    lines += [
        "",
        "## Plots",
        "",
        "![engines](engines.png)",
        "![gap per channel](gap_channels.png)",
        "![remainder](remainder.png)",
        "![held-out segments](holdout_overlay.png)",
        "![closed loop](closed_loop.png)",
        "",
    ]
    return "\n".join(lines)


def _engine_lines(run: MujocoRun, mj: EngineFigures, pb: EngineFigures) -> list[str]:
    return [
        "## The two engines",
        "",
        "| figure (after the first second) | MuJoCo | PyBullet twin |",
        "|---|---|---|",
        f"| distance walked [m] | {mj.distance_m:.3f} | {pb.distance_m:.3f} |",
        f"| mean base height [m] | {mj.base_height_mean_m:.4f} | {pb.base_height_mean_m:.4f} |",
        f"| mean sinkage of a loaded stance foot [mm] | {1e3 * mj.sinkage_mean_m:.2f} | "
        f"{1e3 * pb.sinkage_mean_m:.2f} |",
        f"| travel of a stance foot's centre per stance [mm] (rolling included) | {1e3 * mj.stance_travel_m:.2f} | "
        f"{1e3 * pb.stance_travel_m:.2f} |",
        "",
        "Known differences between the engines (by construction, see `tal_lab/mujoco_hyq.py`):",
        "",
        "- normal contact: MuJoCo's soft constraint (default `solref` 0.02 s / damping ratio 1, `solimp` 0.9-0.95 "
        "over 1 mm), whose force for a given sinkage depends on the effective mass the contact sees; PyBullet's "
        "ground is a 2e6 N/m, 400 N s/m penalty per contact point (course T4); the URDF's own foot pad "
        "(`<contact>` 3e4 N/m, 1e3 N s/m) is used by neither (the bridge overrides it);",
        "- friction: mu = 1 in both; MuJoCo with an elliptic cone and impratio 100, because its default (pyramidal, "
        "impratio 1) let loaded stance feet creep with the trunk (93 mm per stance on this trot, against 2.7 mm in "
        "PyBullet), which is no Coulomb friction; Bullet uses two orthogonal friction directions;",
        "- joint damping: MuJoCo keeps the URDF's 0.1 N m s/rad, the bridge sets it to zero;",
        "- geometry: MuJoCo reads no COLLADA, so only the foot spheres touch the floor (the bridge also has trunk, "
        "hip and upper-leg meshes, which touch only in a fall); shins collide with nothing in both; "
        f"the 1e-6 kg links {', '.join(run.inertia_fixed)} have their off-diagonal inertia set to zero "
        "(MuJoCo refuses the URDF's non-positive-definite tensors);",
        "- integrators: MuJoCo semi-implicit Euler (damping implicit), Bullet's sequential-impulse multibody solver; "
        "both at 1 ms with the same torque path (bridge's actuator model, limits clipped).",
    ]


__all__ = ["engine_figures", "record_twin", "run_mujoco_experiment"]
