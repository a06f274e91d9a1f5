"""Issue 34 items 3 and 6: effects of one leg or one joint. The generator's out-of-library physics (a spring
across a joint, a servo valve's dead band) and the extra mass of a leg's lower link act in PyBullet; the
library's per-leg link-mass variant is named for the right leg by the dynamics search; the benchmark scores
out-of-library cases by their remainder verdict and its place; one-parameter fits are not thrown off by the
few segments whose prediction flips on a contact event (the false remainder alarm of hidden_01)."""

from __future__ import annotations

import numpy as np
import pytest

from tal_core.robot_description import load_robot_description
from tal_core.terrain import load_course
from tal_sim2real.benchmark import acceptance, score
from tal_sim2real.dynamics import _dynamics_with, segment_cost
from tal_sim2real.errors import ModelConfigError
from tal_sim2real.hidden_effects import (
    LOCAL_TYPES,
    OUT_OF_LIBRARY_TYPES,
    HiddenEffect,
    SealedJointEffects,
    _detectability,
    _scaled,
    draw_effect,
    physics_setup,
)
from tal_sim2real.library import CANDIDATES_BY_NAME, VARIANTS_BY_NAME, where_of
from tal_sim2real.links import LowerLinkMasses
from tal_sim2real.measured import BaseTrajectory, MeasuredData
from tal_sim2real.model import SimModel
from tal_sim2real.outcomes import Settings
from tal_sim2real.segments import STATE_SIZE, SegmentPlan, SegmentSimulator
from tal_sim_bridge.physics import Simulation

DT = 1e-3


@pytest.fixture()
def sim():
    simulation = Simulation(load_robot_description("hyq"), load_course("flat_rigid"))
    yield simulation
    simulation.close()


# -- the generator's physics ----------------------------------------------------------------------------------
def test_a_valve_dead_band_removes_small_commands_of_its_joint_only(sim) -> None:
    band = np.zeros(12)
    band[5] = 6.0
    actuators = SealedJointEffects(sim, band, np.zeros(12), np.zeros(12))
    command = np.full(12, 4.0)
    command[5] = 4.0
    assert actuators.delivered_torque(command)[5] == 0.0  # inside the band: nothing
    assert actuators.delivered_torque(command)[4] == pytest.approx(4.0)  # other joints untouched
    command[5] = -15.0
    assert actuators.delivered_torque(command)[5] == pytest.approx(-9.0)  # beyond it: 6 N m less


def test_a_joint_spring_pulls_its_joint_towards_its_rest_angle_in_the_simulation(sim) -> None:
    description = load_robot_description("hyq")
    q0 = description.nominal_joint_positions_rad.copy()
    k, rest = np.zeros(12), q0.copy()
    k[4] = 80.0
    rest[4] = q0[4] + 0.3  # RF hip flexion: pulled to larger angles
    # at the nominal pose (where the robot starts) the spring pushes 80 x 0.3 = 24 N m towards its rest angle
    assert SealedJointEffects(sim, np.zeros(12), k, rest).friction_torque(np.zeros(12))[4] == pytest.approx(24.0)

    def run(with_spring: bool) -> float:
        sim.set_state(np.array([0.0, 0.0, 2.0]), np.array([0.0, 0.0, 0.0, 1.0]), np.zeros(3), np.zeros(3), q0,
                      np.zeros(12))  # in the air: only gravity and the spring
        if with_spring:
            sim.actuators = SealedJointEffects(sim, np.zeros(12), k, rest)
        for _ in range(20):
            sim.step(np.zeros(12))
        sim.actuators = getattr(sim.actuators, "inner", sim.actuators)
        return float(sim.joint_state()[0][4])

    free, sprung = run(False), run(True)
    assert sprung - free > 0.005  # 24 N m for 20 ms on the RF leg: it swings towards the rest angle
    spring = SealedJointEffects(sim, np.zeros(12), k, rest)
    q = sim.joint_state()[0][4]
    assert spring.friction_torque(np.zeros(12))[4] == pytest.approx(-80.0 * (q - rest[4]))


def test_extra_lower_link_mass_is_a_point_mass_at_its_centre_of_mass(sim) -> None:
    links = LowerLinkMasses(sim)
    before = [sim.client.getDynamicsInfo(sim.robot, link) for link in links.links]
    links.apply([0.0, 2.5, 0.0, 0.0])
    after = [sim.client.getDynamicsInfo(sim.robot, link) for link in links.links]
    assert after[1][0] == pytest.approx(before[1][0] + 2.5)
    assert after[1][2] == pytest.approx(before[1][2])  # the URDF's inertia about the centre of mass stays
    assert after[1][3] == pytest.approx(before[1][3])  # and so does the centre of mass
    assert [a[0] for a in (after[0], after[2], after[3])] == pytest.approx([b[0] for b in (before[0], *before[2:])])
    links.apply(np.zeros(4))
    assert sim.client.getDynamicsInfo(sim.robot, links.links[1])[0] == pytest.approx(before[1][0])
    with pytest.raises(ModelConfigError, match="4 finite numbers"):
        links.apply([1.0, 2.0])
    with pytest.raises(ModelConfigError, match="less than 10%"):
        links.apply([0.0, -0.85, 0.0, 0.0])


def test_physics_setup_installs_only_the_physics_effects(sim) -> None:
    assert physics_setup([HiddenEffect("torque_sensor_offset", {"torque_sensor_offset_nm": 3.0, "joint": 2.0})]) is None
    setup = physics_setup(
        [
            HiddenEffect("leg_link_mass", {"leg_link_mass_kg": 2.0, "leg": 2.0}),
            HiddenEffect("valve_dead_band", {"valve_dead_band_nm": 5.0, "joint": 7.0}),
        ]
    )
    nominal = sim.client.getDynamicsInfo(sim.robot, sim.joint_ids[8])[0]
    setup(sim)
    assert sim.client.getDynamicsInfo(sim.robot, sim.joint_ids[8])[0] == pytest.approx(nominal + 2.0)  # LH shin
    assert isinstance(sim.actuators, SealedJointEffects) and sim.actuators.dead_band_nm[7] == 5.0
    with pytest.raises(ValueError, match="12 finite values"):
        SealedJointEffects(sim, np.zeros(3), np.zeros(12), np.zeros(12))


@pytest.mark.parametrize("kind", LOCAL_TYPES)
def test_local_effects_are_drawn_labelled_and_shrunk_with_their_place(kind: str) -> None:
    effect = draw_effect(kind, np.random.default_rng(7))
    label = _detectability(effect, None)  # these labels need no recording
    assert label["detectable"] and label["leg"] in ("LF", "RF", "LH", "RH")
    assert label["out_of_library"] == (kind in OUT_OF_LIBRARY_TYPES)
    if "joint" in effect.values:
        joint = load_robot_description("hyq").joint_names[int(effect.values["joint"])]
        assert label["joint"] == joint and label["leg"] == joint[:2].upper()
    shrunk = _scaled(effect, 0.6)
    assert shrunk.values.get("joint") == effect.values.get("joint") and shrunk.values.get("leg") == effect.values.get(
        "leg"
    )
    size = {
        "joint_spring": "joint_spring_nm_per_rad",
        "valve_dead_band": "valve_dead_band_nm",
        "leg_link_mass": "leg_link_mass_kg",
    }.get(kind)
    if size is not None:  # physics: shrunk towards nominal after a fall
        assert shrunk.values[size] == pytest.approx(0.6 * effect.values[size])
    with pytest.raises(ValueError, match="unknown effect type"):
        draw_effect("backlash_of_everything", np.random.default_rng(0))


# -- the library's per-leg link mass ----------------------------------------------------------------------------
def _hanging_data(n: int = 600) -> MeasuredData:
    description = load_robot_description("hyq")
    sim = Simulation(description, load_course("flat_rigid"))
    try:
        position, quat = sim.base_pose()
    finally:
        sim.close()
    position = position + np.array([0.0, 0.0, 2.0])  # in the air: the legs move on their own
    t = np.arange(n) * DT
    eye = np.tile(np.eye(3), (n, 1, 1))
    base = BaseTrajectory(np.tile(position, (n, 1)), np.tile(quat, (n, 1)), eye, np.zeros((n, 3)), np.zeros((n, 3)),
                          "/ground_truth/odom")
    q = np.tile(description.nominal_joint_positions_rad, (n, 1))
    effort = np.full((n, 12), 5.0)  # [N m] every joint driven (in free fall, without torques, no joint moves)
    return MeasuredData("hanging", list(description.joint_names), t, DT, q, np.zeros((n, 12)), effort, base=base)


def test_the_segment_simulator_applies_a_leg_link_mass_and_restores_it() -> None:
    description = load_robot_description("hyq")
    segments = SegmentSimulator(description, _hanging_data())
    plan = SegmentPlan(np.array([100]), 100, 10)
    model = SimModel.nominal("flat_rigid")
    try:
        plain = segments.predict(model, plan)
        heavy = segments.predict(model, plan, link_mass_kg=np.array([0.0, 3.0, 0.0, 0.0]))
        again = segments.predict(model, plan)
    finally:
        segments.close()
    qd = slice(STATE_SIZE - 12, STATE_SIZE)
    change = np.abs(heavy[..., qd] - plain[..., qd]).max(axis=(0, 1))
    others = np.r_[change[:3], change[6:]]
    assert change[3:6].max() > 3.0 * others.max()  # RF's joints move differently; the others only through the trunk
    np.testing.assert_array_equal(again, plain)


M_LEG = 2.2


class _LegMassStandIn:
    """Joint velocities of leg RF respond to its lower-link mass; the payload moves every leg a little."""

    torque_source = "effort"
    description = None
    simulated_steps = 0

    def __init__(self, data: MeasuredData) -> None:
        self.data = data
        self.q0 = data.q_rad.copy()
        self.torques = np.zeros_like(data.q_rad)

    def predict(self, model: SimModel, plan, q_offset_rad=None, link_mass_kg=None) -> np.ndarray:
        v = model.values()
        mass = np.zeros(4) if link_mass_kg is None else np.asarray(link_mass_kg)
        s = plan.starts[:, None, None].astype(float)
        k = plan.sample_offsets[None, :, None].astype(float)
        j = np.arange(12)[None, None, :]
        out = np.zeros((len(plan.starts), len(plan.sample_offsets), STATE_SIZE))
        out[..., 6] = 1.0
        leg = np.repeat(mass, 3)[None, None, :]
        wave = np.sin(0.013 * s + 0.31 * k + 0.9 * j)
        out[..., 25:37] = 0.3 * (leg - np.where(j // 3 == 1, M_LEG, 0.0)) * wave
        out[..., 25:37] += 0.02 * v["payload_mass_kg"] * np.cos(0.007 * s + 0.17 * k + 2.1 * j)
        out[..., 13:25] = (self.data.q_rad[plan.starts] - self.q0[plan.starts])[:, None, :] * (k / 100.0)
        return out

    def close(self) -> None:
        pass


def _stand_in_data() -> MeasuredData:
    rng = np.random.default_rng(3)
    n = 6000
    t = np.arange(n) * DT
    eye = np.tile(np.eye(3), (n, 1, 1))
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    base = BaseTrajectory(np.zeros((n, 3)), quat, eye, np.zeros((n, 3)), np.zeros((n, 3)), "/ground_truth/odom")
    q = rng.normal(0.0, 2e-4, (n, 12))
    qd = rng.normal(0.0, 0.02, (n, 12))
    return MeasuredData("stand-in", [f"j{i}" for i in range(12)], t, DT, q, qd, np.zeros((n, 12)), base=base)


def test_a_mass_on_one_lower_leg_is_named_for_that_leg_not_as_a_payload() -> None:
    data = _stand_in_data()
    windows = {"identification": (1.0, 4.5), "holdout": (4.5, 6.0)}
    candidates = [CANDIDATES_BY_NAME["payload"], CANDIDATES_BY_NAME["joint_viscous_friction"]]
    result, findings, _ = _dynamics_with(_LegMassStandIn(data), data, candidates, SimModel.nominal(), windows,
                                         Settings())
    named = {f.label: f.values for f in findings if f.status == "named"}
    assert list(named) == ["leg_link_mass[RF]"], result.verdict
    assert named["leg_link_mass[RF]"]["link_mass_rf_kg"] == pytest.approx(M_LEG, rel=0.05)
    assert result.named == ("leg_link_mass[RF]",) and not result.remainder.flagged


def test_the_dynamics_search_is_the_same_with_the_predictions_kept(monkeypatch) -> None:
    """The whole search on a deterministic stand-in (a lower-leg mass: screening, fits, variants, floors):
    the same findings and costs whether predictions asked for again are re-simulated or kept."""
    from tal_sim2real import dynamics

    def search(size: int):
        monkeypatch.setattr(dynamics, "PREDICTION_MEMO_SIZE", size)
        data = _stand_in_data()
        sim = _LegMassStandIn(data)
        calls = []
        predict = sim.predict
        sim.predict = lambda *a, **k: calls.append(1) or predict(*a, **k)
        windows = {"identification": (1.0, 4.5), "holdout": (4.5, 6.0)}
        candidates = [CANDIDATES_BY_NAME["payload"], CANDIDATES_BY_NAME["joint_viscous_friction"]]
        result, findings, _ = dynamics._dynamics_with(sim, data, candidates, SimModel.nominal(), windows, Settings())
        return result, findings, len(calls)

    plain, kept = search(0), search(256)
    assert kept[1] == plain[1]  # findings: status, values, intervals, cost ratios, notes
    assert (kept[0].floor, kept[0].fitted_cost, kept[0].holdout_after, kept[0].verdict) == (
        plain[0].floor,
        plain[0].fitted_cost,
        plain[0].holdout_after,
        plain[0].verdict,
    )
    assert kept[2] < plain[2]


def test_the_link_mass_variant_names_its_leg() -> None:
    variant = VARIANTS_BY_NAME["leg_link_mass"]
    assert variant.base == "payload" and variant.scope == "leg"
    assert where_of(variant.parameter("RH").name, variant) == "RH"


# -- one-parameter fits on a rugged cost ---------------------------------------------------------------------
def test_the_soft_l1_segment_cost_bounds_a_flipped_segments_weight() -> None:
    r = np.zeros((3, 4))
    r[0, 0] = 100.0  # a segment whose touchdown flipped: 1e4 alone
    r[1, 0] = 0.1
    expected = 2.0 * (np.sqrt(1.0 + 1e4) - 1.0) + 2.0 * (np.sqrt(1.01) - 1.0)
    assert segment_cost(r.ravel(), 3, 1.0) == pytest.approx(expected)
    assert segment_cost(0.01 * r.ravel(), 3, 1e6) == pytest.approx(float(np.sum((0.01 * r) ** 2)), rel=1e-5)


@pytest.mark.slow
def test_viscous_friction_of_hidden_01_is_fitted_right_and_leaves_no_false_remainder(tmp_path) -> None:
    """The benchmark's hidden_01 (viscous friction 3.83 N m s/rad, same seed): its plain segment cost is
    rugged (250 at the truth, 4,188 at 3.80, 3,937 at 4.00: a few segments' touchdowns flip), the fit had
    stopped at 4.02 (+5.1%) and the held-out data kept 247 noise floors, a false remainder at RF's knee."""
    from tal_sim2real.dynamics import dynamics_subsystem
    from tal_sim2real.hidden_effects import generate_hidden
    from tal_sim2real.measured import load_measured
    from tal_sim2real.phases import leg_contacts, leg_phases

    truth = 3.8266229371407734
    bag, _ = generate_hidden(
        tmp_path, "hidden_01", [HiddenEffect("joint_viscous_friction", {"joint_viscous_friction_nms_per_rad": truth})],
        seed=1)
    description = load_robot_description("hyq")
    data = load_measured(bag, description)
    settings = Settings()
    t0, t1 = float(data.t_s[0]), float(data.t_s[-1])
    holdout = t1 - settings.holdout_fraction * (t1 - t0)
    windows = {"identification": (t0 + settings.settle_s, holdout), "holdout": (holdout, t1)}
    nominal = SimModel.nominal("flat_rigid")
    phases = leg_phases(leg_contacts(data, description, nominal), data.dt_s)
    result, findings, _ = dynamics_subsystem(data, description, [CANDIDATES_BY_NAME["joint_viscous_friction"]],
                                             nominal, windows, settings, phases)
    named = {f.label: f.values for f in findings if f.status == "named"}
    assert named["joint_viscous_friction"]["joint_viscous_friction_nms_per_rad"] == pytest.approx(truth, rel=0.01)
    assert not result.remainder.flagged, result.verdict
    assert result.verdict.startswith("named joint_viscous_friction")


# -- benchmark: out-of-library cases -----------------------------------------------------------------------------
def _outcome(named: dict, remainders: dict) -> dict:
    return {"named": named, "remainders": remainders, "gap_before": 10.0, "gap_after": 5.0, "elapsed_s": 1.0}


def _spring_label() -> dict:
    effect = {
        "kind": "valve_dead_band",
        "values": {"valve_dead_band_nm": 6.0, "joint": 5.0},
        "detectable": True,
        "out_of_library": True,
        "leg": "RF",
        "joint": "rf_kfe_joint",
    }
    return {"name": "outlib_01", "effects": [effect]}


def test_an_out_of_library_case_needs_a_remainder_verdict_at_the_right_joint() -> None:
    def remainder(flagged: bool, ratio: float, leg: str, joint: str) -> dict:
        return {"flagged": flagged, "ratio": ratio, "top_leg": leg, "top_joint": joint}

    label = _spring_label()
    right = score(
        _outcome(
            {"leg_torque_gain": {"torque_gain_rf": 0.9}},
            {
                "torque_path": remainder(True, 40.0, "RF", "rf_kfe_joint"),
                "dynamics": remainder(True, 5.0, "LH", "lh_kfe_joint"),  # the larger ratio decides where
            },
        ),
        label,
    )
    elsewhere = score(_outcome({}, {"torque_path": remainder(True, 8.0, "LH", "lh_hfe_joint")}), label)
    silent = score(_outcome({"torque_gain": {"torque_gain": 0.95}}, {"torque_path": remainder(False, 2.0, "", "")}),
                   label)
    quiet = score(_outcome({}, {"torque_path": remainder(False, 1.5, "", "")}), label)
    assert right["localised"] and not right["named_without_remainder"]
    assert not elsewhere["localised"] and elsewhere["remainder_flagged"]
    assert silent["named_without_remainder"] and silent["no_remainder_verdict"]
    assert not quiet["named_without_remainder"] and quiet["no_remainder_verdict"]
    table = {row[0]: row for row in acceptance([right, elsewhere, silent, quiet])}
    named = next(k for k in table if k.startswith("effects outside the library named"))
    unflagged = next(k for k in table if k.startswith("effects outside the library with no remainder"))
    local = next(k for k in table if k.startswith("remainder localised"))
    assert table[named][1].startswith("1/4") and not table[named][3]
    assert table[unflagged][1].startswith("2/4") and not table[unflagged][3]
    assert table[local][1].startswith("1/4") and not table[local][3]


def test_the_benchmark_scores_a_leg_link_mass_as_a_variant() -> None:
    effect = {"kind": "leg_link_mass", "values": {"leg_link_mass_kg": 2.0, "leg": 1.0}, "detectable": True,
              "out_of_library": False, "leg": "RF", "joint": ""}
    label = {"name": "variant_02", "effects": [effect]}
    outcome = {**_outcome({"leg_link_mass": {"link_mass_rf_kg": 2.3}}, {}), "where": {"leg_link_mass": "RF"}}
    row = score(outcome, label)
    assert row["variant_named_where"] == {"leg_link_mass": True} and not row["out_of_library"]
    assert row["param_errors"]["leg_link_mass"] == pytest.approx(0.15)
    assert row["within_tolerance"]["leg_link_mass"]  # 25% for masses, as the payload
    payload = score(_outcome({"payload": {"payload_mass_kg": 2.0}}, {}), label)
    assert payload["variant_named_where"] == {"leg_link_mass": False}
