"""ViTAL in the closed loop: the shin collision check on real PyBullet geometry, and a short lockstep run
with VFA + VPA whose trace, report and plots are complete."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from tal_lab.vital.vital_experiments import (
    START_S,
    VitalRun,
    _variation_per_metre,
    experiment_runs,
    plot,
    run_vital,
    wilson_interval,
    write_report,
)
from tal_lab.vital.vital_loop import VitalLoop, VitalLoopSettings, collision_events

from tal_core.robot_model import RobotModel
from tal_core.terrain import load_course
from tal_perception.errors import VpaConfigError


@pytest.fixture(scope="module")
def stairs():
    return load_course("vital_stairs")


def _posed_simulation(hyq: RobotModel, course, x: float, z: float):
    from tal_sim_bridge.physics import Simulation

    sim = Simulation(hyq.description, course, initial_xy=(x, 0.0))
    sim._reset_base_pose([x, 0.0, z], [0.0, 0.0, 0.0, 1.0])  # the nominal joint angles, base placed by hand
    return sim


def test_shins_in_the_riser_are_collisions_and_shins_above_the_ground_are_not(hyq: RobotModel, stairs) -> None:
    loop = VitalLoop(stairs, hyq, VitalLoopSettings(vfa=False, pose_source="none"))
    nominal = float(hyq.nominal_base_height_m)
    sim = _posed_simulation(hyq, stairs, 0.0, nominal + 0.05)  # flat ground, feet 5 cm up
    try:
        hit, depth = loop.shin_collisions(sim)
        assert not hit.any() and (depth < -0.03).all()
    finally:
        sim.close()
    # Front feet just past the first riser (x = 1.0 m), 6 cm above the floor and so 4 cm below the tread:
    # the front shins' lower ends are inside the step, the hind legs stand clear over the floor.
    sim = _posed_simulation(hyq, stairs, 0.0, nominal + 0.06)
    try:
        front_x = float(np.mean([c.position_m[0] for c in sim.foot_contacts()[:2]]))
    finally:
        sim.close()
    sim = _posed_simulation(hyq, stairs, 1.03 - front_x, nominal + 0.06)
    try:
        hit, depth = loop.shin_collisions(sim)
        assert hit.tolist() == [True, True, False, False], depth
    finally:
        sim.close()


def test_collision_events_count_onsets_per_leg() -> None:
    flags = np.zeros((6, 4), dtype=bool)
    flags[0, 0] = flags[1, 0] = True  # one event from the first sample on
    flags[3, 0] = True  # a second one
    flags[2:5, 2] = True
    assert collision_events(flags).tolist() == [2, 0, 1, 0]
    assert collision_events(np.zeros((0, 4), dtype=bool)).tolist() == [0, 0, 0, 0]


def test_pose_variation_is_total_variation_per_metre() -> None:
    x = np.linspace(0.0, 2.0, 5)
    z = np.array([0.6, 0.65, 0.6, 0.6, 0.7])  # 0.05 + 0.05 + 0.1 = 0.2 m over 2 m
    pitch = np.array([0.0, 10.0, 10.0, 0.0, 0.0])
    dz, dpitch = _variation_per_metre(x, z, pitch)
    assert dz == pytest.approx(0.1) and dpitch == pytest.approx(10.0)
    assert all(math.isnan(v) for v in _variation_per_metre(np.zeros(3), z[:3], pitch[:3]))


def test_settings_and_experiment_list_are_checked() -> None:
    with pytest.raises(VpaConfigError, match="pose_source"):
        VitalLoopSettings(pose_source="plane")
    with pytest.raises(VpaConfigError, match="heightmap_period_s"):
        VitalLoopSettings(heightmap_period_s=0.0)
    runs = experiment_runs()
    assert set(runs) == {"speeds", "cnn", "tbr", "gaps", "rough", "horizon", "cost", "centre", "pose_filter",
                         "step_frequency", "starts", "swing_model", "learned", "moment_weight"}
    assert all(r.loop.vpa_use_cnn for r in runs["cnn"]) and not any(r.loop.vpa_use_cnn for r in runs["speeds"])
    names = [r.name for key in ("speeds", "cnn", "tbr", "gaps", "rough") for r in runs[key]]
    shared = {f"stairs_0.2_x{x0:+.1f}" for x0 in (-0.1, 0.0, 0.1)}
    assert len(set(names)) == len(names) - sum(names.count(n) - 1 for n in shared)
    for key, variant in (("horizon", "single_horizon"), ("cost", "c_sum")):  # 9 starts each at 0.4 m/s
        assert [r.name for r in runs[key][:9]] == [r.name for r in runs["pose_filter"][:9]]
        assert [r.initial_x_m for r in runs[key][:9]] == [-0.1, 0.0, 0.1, -0.2, -0.15, -0.05, 0.05, 0.15, 0.2]
        assert all(variant in r.name for r in runs[key][9:]) and len(runs[key]) == 18
    assert [r.speed_mps for r in runs["speeds"]] == [v for v in (0.2, 0.3, 0.4, 0.5) for _ in range(3)]
    assert [r.initial_x_m for r in runs["speeds"][:3]] == [-0.1, 0.0, 0.1]
    assert all(r.k_feedback_s == 0.12 and r.contact_feedback for r in runs["speeds"])
    assert sum(r.loop is not None and r.loop.pose_source == "tbr" for r in runs["tbr"]) == 3
    # centre: the speeds runs' configuration (footholds under the CoM, pair compensation) against the previous
    # one (about the hips, none), from 3 starts at 0.2 and 0.3 m/s; the shared runs are the same.
    centre = {r.name: r for r in runs["centre"]}
    assert all(centre[r.name] == r for r in runs["speeds"] if r.speed_mps < 0.35)
    for config, pair in (("com", 0.08), ("hips", 0.0)):
        members = [r for r in runs["centre"] if r.foothold_centre == config]
        assert [sum(r.speed_mps == v for r in members) for v in (0.2, 0.3, 0.4)] == [3, 3, 0]
        assert all(r.loop.vfa_planner.pair_compensation_m == pair for r in members)
    assert len(centre) == len(runs["centre"]) == 12 and "stairs_0.3_hips_x-0.1" in centre
    # pose_filter: the runs' body-pose filter against the controller's default, 9 starts at 0.4 m/s.
    pose = runs["pose_filter"]
    assert all(r.pose_bandwidth_rad_s == 6.0 and r.max_height_rate_m_s == 0.25 for r in runs["speeds"])
    default = [r for r in pose if r.pose_bandwidth_rad_s is None]
    assert len(default) == 9 and all(r.max_height_rate_m_s is None and "default_filter" in r.name for r in default)
    assert [r for r in pose if r.pose_bandwidth_rad_s is not None] == runs["horizon"][:9]
    # 0.5 m/s trots at 1.8 Hz, slower runs at the preset's; step_frequency compares the two at 0.5 m/s.
    assert [r.step_frequency_hz for r in runs["speeds"][::3]] == [None, None, None, 1.8]
    steps = runs["step_frequency"]
    assert len(steps) == 18 and all(r.speed_mps == 0.5 for r in steps)
    assert [r.step_frequency_hz for r in steps] == [1.8] * 9 + [None] * 9 and "1.5hz" in steps[-1].name
    # starts: the speeds runs from 9 starts; at 0.4 and 0.5 m/s the very runs of pose_filter and step_frequency.
    starts = runs["starts"]
    assert [sum(r.speed_mps == v for r in starts) for v in (0.2, 0.3, 0.4, 0.5)] == [9, 9, 9, 9]
    assert set(runs["speeds"]) <= set(starts)
    assert [r for r in starts if r.speed_mps == 0.4] == runs["pose_filter"][:9]
    assert [r for r in starts if r.speed_mps == 0.5] == runs["step_frequency"][:9]
    variants = ("swing_model", "learned", "moment_weight")
    everything = {r.name for key, group in runs.items() if key not in variants for r in group}
    assert len(everything - {r.name for key, group in runs.items()
                             if key not in ("starts", *variants) for r in group}) == 12
    # swing_model: the starts runs, then the same 36 with the terrain swing model and peak weighting only.
    swing = runs["swing_model"]
    assert swing[:36] == starts and len(swing) == 72
    for thesis, terrain in zip(swing[:36], swing[36:]):
        assert terrain.name == thesis.name.replace("_x", "_terrain_swing_x")
        assert (thesis.loop.vpa.swing_hip_model, thesis.loop.vpa.leg_weighting) == ("level", "none")
        assert terrain.loop.vpa == replace(thesis.loop.vpa, swing_hip_model="terrain", leg_weighting="peak")
        assert replace(terrain, name=thesis.name, loop=thesis.loop) == thesis
    # moment_weight: the starts runs, then the same 36 with the moment error weighted 10 only.
    moment = runs["moment_weight"]
    assert moment[:36] == starts and len(moment) == 72 and all(r.moment_weight == 1.0 for r in starts)
    for thesis, weighted in zip(moment[:36], moment[36:]):
        assert weighted.name == thesis.name.replace("_x", "_moment10_x") and weighted.moment_weight == 10.0
        assert replace(weighted, name=thesis.name, moment_weight=1.0) == thesis
    with pytest.raises(ValueError, match="moment_weight must be finite and > 0"):
        replace(starts[0], moment_weight=0.0)
    # learned: the speeds runs' configuration with both CNNs, the VFA's verified (0.2-0.5 m/s) and alone (0.2).
    learned = runs["learned"]
    assert len(learned) == 45
    assert [r.speed_mps for r in learned] == [v for v in (0.2, 0.3, 0.4, 0.5, 0.2) for _ in range(9)]
    assert [r.initial_x_m for r in learned[:9]] == [r.initial_x_m for r in starts[:9]]
    for run in learned:
        alone = "cnns_unverified" in run.name
        assert run.loop.vfa_selector == ("cnn_unverified" if alone else "cnn") and run.loop.vpa_use_cnn
        same = next(r for r in starts if r.speed_mps == run.speed_mps and r.initial_x_m == run.initial_x_m)
        assert replace(run, name=same.name, loop=same.loop) == same
        assert replace(run.loop, vfa_selector="exact", vpa_use_cnn=False) == same.loop
    # The forward command stops 0.6 m past the goal: no run walks off its course (stairs: x <= 8 m).
    for r in runs["speeds"]:
        assert r.initial_x_m + r.speed_mps * (r.stop_s - START_S) == pytest.approx(r.goal_x_m + r.past_goal_m)
        assert r.duration_s == pytest.approx(r.stop_s + r.hold_s)


def test_wilson_interval_brackets_the_rate_and_stays_in_the_unit_interval() -> None:
    low, high = wilson_interval(5, 9)
    assert low < 5 / 9 < high
    assert (low, high) == pytest.approx((0.267, 0.811), abs=1e-3)  # textbook value for 5 of 9
    assert wilson_interval(9, 9)[1] == pytest.approx(1.0) and 0.66 < wilson_interval(9, 9)[0] < 0.71
    assert wilson_interval(0, 9)[0] == pytest.approx(0.0) and wilson_interval(0, 0) == (0.0, 1.0)
    assert wilson_interval(3, 3)[0] < wilson_interval(9, 9)[0]  # fewer trials, wider interval
    with pytest.raises(ValueError, match="successes"):
        wilson_interval(4, 3)


@pytest.mark.slow
def test_a_short_stairs_run_with_vfa_and_vpa_is_traced_reported_and_plotted(tmp_path) -> None:
    """2.5 s of lockstep trot towards the stairs: every tick traced, VPA updates at 20 Hz from the first
    map on, the exact safe-foothold monitor sampled, no collisions on the flat approach."""
    run = VitalRun("smoke", "vital_stairs", 0.3, VitalLoopSettings(monitor_period_s=0.5), goal_x_m=0.1)
    result = run_vital(run, progress=False, max_sim_s=2.5)
    series = result.series
    assert len(series["t"]) == 625 and not result.fell and result.success
    assert np.isfinite(series["pose_reference"][-1]).all()
    assert 0.4 < series["pose_reference"][-1][0] < 0.8  # base height [m] over the flat floor
    assert np.isfinite(series["safe"][-1]).all() and (series["safe"][-1] > 0).all()
    assert sum(result.leg_collisions) == 0 and sum(result.foot_collisions) == 0
    assert result.decisions > 0 and result.vpa_compute_median_ms > 0
    # the swing_model report and figure: the same run under both names (the figure's trajectories need 0.5 m/s)
    fast = replace(run, name="stairs_0.5_x+0.0", speed_mps=0.5)
    tagged = replace(fast, name="stairs_0.5_terrain_swing_x+0.0")
    results = {"smoke": result, fast.name: replace(result, name=fast.name),
               tagged.name: replace(result, name=tagged.name, success=False)}
    alone = replace(run, name="stairs_0.3_cnns_unverified_x+0.0")
    results[alone.name] = replace(result, name=alone.name, leg_collisions=[0, 2, 0, 0],
                                  recovered_wrench_misses=[[4.0, 4.1, 420.0, 1.234], [7.0, 7.2, 350.0, 3.1]])
    runs = {"speeds": [run], "cost": [run, replace(run, name="smoke")], "swing_model": [fast, tagged],
            "learned": [run, alone]}
    write_report(tmp_path, runs, results)
    plot(tmp_path, runs, results)
    report = (tmp_path / "closed_loop.md").read_text()
    assert "| smoke | 0.3 | yes |" in report
    assert "| 0.5 | 1 of 1 |" in report and "| 0.5 | 0 of 1 |" in report  # thesis' model, then the terrain one
    learned = report.split("## Both CNNs in the loop")[1]  # verified (the smoke run), then the CNN alone
    assert learned.index("VFA CNN verified") < learned.index("| 0.3 | 1 of 1 | 21-100 % | 0 |")
    assert learned.index("VFA CNN alone") < learned.index("| 0.3 | 1 of 1 | 21-100 % | 2 |")
    # recovered wrench misses: a run's count, and the sum in its speed summary
    assert result.recovered_wrench_misses == []  # the flat approach: no wrench miss
    alone_summary = next(line for line in learned.splitlines() if line.startswith("| 0.3 | 1 of 1 | 21-100 % | 2 |"))
    alone_row = next(line for line in learned.splitlines() if line.startswith(f"| {alone.name} |"))
    assert alone_row.split("|")[-3].strip() == "2" and alone_summary.endswith("| 2 |")
    assert (tmp_path / "vital_stairs_speeds.png").stat().st_size > 10_000
    assert (tmp_path / "vital_swing_model.png").stat().st_size > 10_000
    assert (tmp_path / "closed_loop.json").exists()
