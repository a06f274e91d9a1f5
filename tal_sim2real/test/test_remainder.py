"""The honest remainder (issue 34, items 1-2): the verdict is never a plain "named" while the held-out residual
stays above the noise floor re-estimated with the updated model; the remainder is localised per joint, leg
and gait phase; the dynamics search re-estimates the floor after each accepted fit; the closed-loop re-run
uses the recording's gait; the benchmark counts an out-of-library case named without a remainder verdict.

Small synthetic cases (no physics re-simulation; the dynamics search runs against a stand-in simulator)."""

from __future__ import annotations

import numpy as np
import pytest

from tal_core.robot_description import load_robot_description
from tal_sim2real.benchmark import acceptance, score
from tal_sim2real.dynamics import _dynamics_with
from tal_sim2real.library import CANDIDATES_BY_NAME
from tal_sim2real.measured import BaseTrajectory, MeasuredData
from tal_sim2real.model import SimModel
from tal_sim2real.outcomes import Settings
from tal_sim2real.phases import PHASES, infer_gait, leg_phases
from tal_sim2real.remainder import ISOLATED_SEGMENTS, REMAINDER_FACTOR, Remainder, judge, localise, set_aside
from tal_sim2real.segments import STATE_SIZE
from tal_sim2real.subsystems import torque_path_subsystem

DT = 1e-3


def test_a_residual_above_the_floor_is_never_a_plain_named() -> None:
    explained = judge(Remainder("dynamics", before=1e5, after=1.2e3, floor=1e3), ("payload",), at_floor=False)
    assert not explained.flagged and explained.verdict.startswith("named payload")
    partly = judge(Remainder("dynamics", before=1e5, after=2e4, floor=1e3), ("payload",), at_floor=False)
    assert partly.flagged and partly.verdict.startswith("partly explained")
    closest = judge(Remainder("torque_path", before=2e5, after=1.4e5, floor=1.6e3), ("torque_gain",), False)
    assert closest.flagged and closest.verdict.startswith("not explained by the library")
    nothing = judge(Remainder("dynamics", before=3e4, after=3e4, floor=1e3), (), at_floor=False)
    assert nothing.verdict.startswith("not explained by the library")
    free = judge(Remainder("dynamics", before=1.1e3, after=1.1e3, floor=1e3), (), at_floor=True)
    assert free.verdict.startswith("no missing effect") and not free.flagged
    for r in (partly, closest, nothing):
        assert r.ratio > REMAINDER_FACTOR and "named" not in r.verdict.split(":")[0]


def test_the_remainder_is_localised_to_the_joint_leg_and_phase_that_hold_it() -> None:
    rng = np.random.default_rng(0)
    shape = (20, 10, 14)  # segments, samples, components: 2 base components then 12 joints
    floor = np.ones(shape)
    cost = rng.chisquare(1, shape)
    joint_of = np.array([-1, -1, *range(12)])
    phase = rng.integers(0, 3, shape)
    knee = 2 + 8  # component of joint 8 (LH knee)
    cost[..., knee] += 30.0 * (phase[..., knee] == PHASES.index("touchdown"))
    channels = {"base": joint_of < 0, "joints": joint_of >= 0}
    names = [f"j{j}" for j in range(12)]
    r = localise(Remainder("dynamics", 1.0, 1.0, 1.0), cost, floor, channels, names, joint_of, phase)
    assert r.top("joint") == "j8" and r.top("leg") == "LH" and r.top("phase") == "touchdown"
    assert r.top("channel") == "joints"
    assert r.by_leg["LH"].share > 0.8 and r.by_joint["j8"].ratio > 5.0


def _segments(excess_per_segment: list[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-element cost and floor of segments at the floor plus the given excess, put on joint 5's velocity."""
    n = len(excess_per_segment)
    floor = np.ones((n, 10, 14))
    cost = floor.copy()
    cost[:, :, 2 + 5] += np.asarray(excess_per_segment)[:, None] / 10.0
    return cost, floor, np.arange(n) * 0.2 + 6.0


def test_an_isolated_contact_event_is_set_aside_and_listed_not_called_a_remainder() -> None:
    # 20 held-out segments at the floor but two (a touchdown each, 30 and 40 floors): 4.4 floors in all (the
    # benchmark's hidden_11, its effect named right: 4.0); without the two the model is at the floor
    excess = [0.0] * 20
    excess[1], excess[4] = 29.0 * 140, 39.0 * 140
    cost, floor, starts = _segments(excess)
    r = Remainder("dynamics", before=1e5, after=float(cost.sum()), floor=float(floor.sum()))
    joint_of = np.array([-1, -1, *range(12)])
    keep = set_aside(r, cost, floor, starts, [f"j{j}" for j in range(12)], joint_of)
    assert r.ratio > REMAINDER_FACTOR
    assert int(ISOLATED_SEGMENTS * 20) == 2 and (~keep).sum() == 2 and not keep[1] and not keep[4]
    assert [e.start_s for e in r.isolated] == [6.2, 6.8] and all(e.joint == "j5" for e in r.isolated)
    assert r.isolated[1].share == pytest.approx(39 / 68) and r.isolated[1].ratio == pytest.approx(40.0)
    assert r.systematic_ratio == pytest.approx(1.0)
    judged = judge(r, ("actuator_lag",), at_floor=False)
    assert not judged.flagged and judged.verdict.startswith("named actuator_lag")


def test_a_remainder_spread_over_the_segments_is_still_a_remainder() -> None:
    # an out-of-library effect: every segment 5-40 floors above; setting the two worst aside leaves it flagged
    cost, floor, starts = _segments([140.0 * k for k in np.linspace(5.0, 40.0, 20)])
    r = Remainder("dynamics", before=float(cost.sum()), after=float(cost.sum()), floor=float(floor.sum()))
    set_aside(r, cost, floor, starts, [f"j{j}" for j in range(12)], np.array([-1, -1, *range(12)]))
    assert len(r.isolated) == 2 and r.systematic_ratio > REMAINDER_FACTOR
    judged = judge(r, (), at_floor=False)
    assert judged.flagged and judged.verdict.startswith("not explained by the library")
    # fewer than ten segments: nothing is set aside
    short = Remainder("dynamics", 1.0, 1.0, 1.0)
    set_aside(short, cost[:9], floor[:9], starts[:9], [f"j{j}" for j in range(12)], np.array([-1, -1, *range(12)]))
    assert not short.isolated and short.systematic_ratio == short.ratio
    with pytest.raises(ValueError, match="segment starts"):
        set_aside(short, cost, floor, starts[:3], [], np.array([-1, -1, *range(12)]))


# -- torque path: a gain on one leg's torques is not the library's global gain ------------------------------
def _torque_data(leg_gain: dict[int, float], seed: int = 0) -> MeasuredData:
    description = load_robot_description("hyq")
    rng = np.random.default_rng(seed)
    n = 4000
    t = np.arange(n) * DT
    q = np.tile(description.nominal_joint_positions_rad, (n, 1))
    cmd_t = t[::4]
    phase = rng.uniform(0, 2 * np.pi, 12)
    command = 30.0 * np.sin(2 * np.pi * 1.5 * cmd_t[:, None] + phase[None, :])
    data = MeasuredData("synthetic", list(description.joint_names), t, DT, q, np.zeros((n, 12)), None)
    data.command_t_s, data.command_nm = cmd_t, command
    gains = np.ones(12)
    for leg, g in leg_gain.items():
        gains[3 * leg : 3 * leg + 3] = g
    data.effort_nm = data.command_in_force() * gains + rng.normal(0.0, 0.3, (n, 12))
    return data


def _torque_run(data: MeasuredData):
    description = load_robot_description("hyq")
    candidates = [CANDIDATES_BY_NAME[k] for k in ("actuator_delay", "actuator_lag", "torque_gain", "torque_limit")]
    index = np.arange(100, len(data.t_s))
    held = (index // 500) % 4 == 3
    contacts = np.ones((len(data.t_s), 4), dtype=bool)
    contacts[(data.t_s % 0.6) < 0.25, 1] = False  # RF swings now and then
    return torque_path_subsystem(
        data, description, candidates, index[~held], index[held], Settings(), leg_phases(contacts, DT)
    )


def test_a_global_torque_gain_is_named_and_explained_to_the_floor() -> None:
    result, _ = _torque_run(_torque_data({0: 0.85, 1: 0.85, 2: 0.85, 3: 0.85}))
    assert result.named == ("torque_gain",)
    assert not result.remainder.flagged and result.verdict.startswith("named torque_gain")
    assert result.remainder.ratio < 1.5


def test_a_gain_on_one_leg_is_named_per_leg_for_that_leg() -> None:
    # issue 34 item 3: the remainder of the global gain points at RF, where the per-leg variant is tried; the
    # information criterion prefers it to the global gain (which would leave RF's excess and spoil the others)
    result, findings = _torque_run(_torque_data({1: 0.85}))
    named = {f.label: f for f in findings if f.status == "named"}
    assert list(named) == ["leg_torque_gain[RF]"]
    assert named["leg_torque_gain[RF]"].values["torque_gain_rf"] == pytest.approx(0.85, rel=0.01)
    assert result.named == ("leg_torque_gain[RF]",)
    assert not result.remainder.flagged and result.verdict.startswith("named leg_torque_gain[RF]")


# -- dynamics: the floor is re-estimated after each accepted fit --------------------------------------------
M_TRUE, B_TRUE = 8.0, 2.0


class _StandIn:
    """A simulator stand-in: joint velocities respond linearly to payload mass and viscous friction, and the
    noise floor of a model far from the true payload is inflated (its noise perturbations grow), as a
    PyBullet floor estimated with the nominal ground/payload is (4.2e5 against 2.0e3)."""

    torque_source = "effort"
    description = None
    simulated_steps = 0

    def __init__(self, data: MeasuredData) -> None:
        self.data = data
        self.q0 = data.q_rad.copy()
        self.torques = np.zeros_like(data.q_rad)

    def predict(self, model: SimModel, plan, **variants) -> np.ndarray:
        v = model.values()
        s = plan.starts[:, None, None].astype(float)
        k = plan.sample_offsets[None, :, None].astype(float)
        j = np.arange(12)[None, None, :]
        out = np.zeros((len(plan.starts), len(plan.sample_offsets), STATE_SIZE))
        out[..., 6] = 1.0
        p1 = np.sin(0.013 * s + 0.31 * k + 0.9 * j)
        p2 = np.cos(0.007 * s + 0.17 * k + 2.1 * j)
        out[..., 25:37] = 0.14 * (v["joint_viscous_friction_nms_per_rad"] - B_TRUE) * p1
        out[..., 25:37] += 0.12 * (v["payload_mass_kg"] - M_TRUE) * p2
        gain = 1.0 + 11.0 * abs(v["payload_mass_kg"] - M_TRUE)
        perturbation = (self.data.q_rad[plan.starts] - self.q0[plan.starts])[:, None, :]
        out[..., 13:25] = gain * perturbation * (k / 100.0)  # grows over the 0.1 s horizon
        return out

    def close(self) -> None:
        pass


def _stand_in_data() -> MeasuredData:
    rng = np.random.default_rng(3)
    n = 6000
    t = np.arange(n) * DT
    q = rng.normal(0.0, 2e-4, (n, 12))
    qd = rng.normal(0.0, 0.02, (n, 12))
    eye = np.tile(np.eye(3), (n, 1, 1))
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    base = BaseTrajectory(np.zeros((n, 3)), quat, eye, np.zeros((n, 3)), np.zeros((n, 3)), "/ground_truth/odom")
    return MeasuredData("stand-in", [f"j{i}" for i in range(12)], t, DT, q, qd, np.zeros((n, 12)), base=base)


def test_the_search_re_estimates_the_floor_and_names_both_effects() -> None:
    """Payload alone leaves a cost below the floor estimated with the nominal model, but far above the floor
    re-estimated with the payload: the search must go on and fit the pair."""
    data = _stand_in_data()
    sim = _StandIn(data)
    candidates = [CANDIDATES_BY_NAME["payload"], CANDIDATES_BY_NAME["joint_viscous_friction"]]
    windows = {"identification": (1.0, 4.5), "holdout": (4.5, 6.0)}
    result, findings, _ = _dynamics_with(sim, data, candidates, SimModel.nominal(), windows, Settings())
    named = {f.candidate: f.values for f in findings if f.status == "named"}
    assert set(named) == {"payload", "joint_viscous_friction"}, result.verdict
    assert named["payload"]["payload_mass_kg"] == pytest.approx(M_TRUE, rel=0.05)
    assert named["joint_viscous_friction"]["joint_viscous_friction_nms_per_rad"] == pytest.approx(B_TRUE, rel=0.05)
    assert result.floor_updated < 0.1 * result.floor  # the nominal model's floor was far too high
    assert not result.remainder.flagged and result.verdict.startswith("named")


# -- closed-loop re-run: the recording's gait ---------------------------------------------------------------
def _contacts(pattern: str, n: int = 6000) -> np.ndarray:
    t = np.arange(n) * DT
    contacts = np.ones((n, 4), dtype=bool)
    if pattern == "trot":
        phase = (t * 1.5) % 1.0
        contacts[:, [0, 3]] = ~(phase < 0.4)[:, None]
        contacts[:, [1, 2]] = ~((phase >= 0.5) & (phase < 0.9))[:, None]
    elif pattern == "crawl":
        phase = (t * 0.5) % 1.0
        for leg, offset in enumerate((0.25, 0.75, 0.0, 0.5)):
            contacts[:, leg] = ((phase - offset) % 1.0) >= 0.2
    return contacts


@pytest.mark.parametrize("gait", ["trot", "crawl", "stand"])
def test_the_gait_is_read_from_the_contacts_and_used_by_the_re_run(gait: str) -> None:
    from tal_sim2real.replay import _config

    contacts = _contacts(gait)
    assert infer_gait(contacts, np.arange(len(contacts)) * DT) == gait
    data = _stand_in_data()
    config = _config(SimModel.nominal(), [(0.0, 0.0, 0.0, 0.0)], data, infer_gait(contacts, data.t_s))
    assert config.gait == gait
    phases = leg_phases(contacts, DT)
    if gait != "stand":
        assert {0, 1, 2} <= set(np.unique(phases))


# -- benchmark scoring --------------------------------------------------------------------------------------
def _outcome(named: dict, flagged: bool, leg: str = "", joint: str = "") -> dict:
    remainder = {"ratio": 20.0 if flagged else 1.0, "flagged": flagged, "top_leg": leg, "top_joint": joint}
    return {
        "named": named,
        "remainders": {"torque_path": remainder},
        "gap_before": 10.0,
        "gap_after": 5.0,
        "elapsed_s": 1.0,
    }


def test_the_benchmark_counts_an_out_of_library_case_named_without_a_remainder_verdict() -> None:
    label = {
        "name": "outlib_00",
        "effects": [
            {
                "kind": "joint_spring",  # a kind the library has no variant for
                "values": {"joint_spring_nm_per_rad": 50.0, "joint_spring_rest_rad": 0.9, "joint": 4.0},
                "detectable": True,
                "out_of_library": True,
                "leg": "RF",
                "joint": "rf_hfe_joint",
            }
        ],
    }
    silent = score(_outcome({"torque_gain": {"torque_gain": 0.96}}, flagged=False), label)
    honest = score(_outcome({"torque_gain": {"torque_gain": 0.96}}, flagged=True, leg="RF"), label)
    assert silent["named_without_remainder"] and not silent["localised"]
    assert not honest["named_without_remainder"] and honest["localised"]
    table = {row[0]: row for row in acceptance([silent, honest])}
    key = next(k for k in table if k.startswith("effects outside the library named"))
    assert table[key][1].startswith("1/2") and not table[key][3]
    local = next(k for k in table if k.startswith("remainder localised"))
    assert table[local][1].startswith("1/2")
    # out-of-library datasets do not count as single library effects
    assert next(v for k, v in ((r[0], r[1]) for r in table.values()) if k.startswith("right effect")) == "n/a"


# -- per-leg and per-joint variants (issue 34 item 3) -------------------------------------------------------
def test_the_information_criterion_counts_effective_samples_and_charges_parameters() -> None:
    from tal_sim2real.fitting import effective_samples, information_criterion

    rng = np.random.default_rng(1)
    white = rng.normal(size=(5000, 3))
    walk = np.cumsum(rng.normal(size=(5000, 3)), axis=0)
    assert effective_samples(white) == pytest.approx(15000, rel=0.1)
    assert effective_samples(walk) < 0.01 * 15000  # a slow model error is few independent samples
    # the same cost with one more parameter is worse by log(n); a cost drop worth more than that wins
    assert information_criterion(100.0, 1000, 2) - information_criterion(100.0, 1000, 1) == pytest.approx(np.log(1000))
    assert information_criterion(95.0, 1000, 2) < information_criterion(100.0, 1000, 1)


@pytest.mark.parametrize("leg, gain", [(3, 1.15), (0, 0.8)])
def test_a_one_leg_gain_is_named_for_its_leg_whichever_leg(leg: int, gain: float) -> None:
    _, findings = _torque_run(_torque_data({leg: gain}, seed=leg))
    named = [f for f in findings if f.status == "named"]
    assert [f.label for f in named] == [f"leg_torque_gain[{('LF', 'RF', 'LH', 'RH')[leg]}]"]
    assert next(iter(named[0].values.values())) == pytest.approx(gain, rel=0.01)


def test_a_global_gain_on_all_legs_stays_global_even_with_one_leg_slightly_off() -> None:
    # 0.85 everywhere, 0.86 on RF: the per-leg parameter is not worth its cost... unless the data insist; a
    # 1% difference at 0.3 N m noise is below what the criterion pays for
    result, findings = _torque_run(_torque_data({0: 0.85, 1: 0.851, 2: 0.85, 3: 0.85}))
    assert [f.label for f in findings if f.status == "named"] == ["torque_gain"]
    assert result.named == ("torque_gain",)


class _EncoderStandIn(_StandIn):
    """Joint velocities that depend on the true start angle (the measured one minus the encoder offset)."""

    def predict(self, model: SimModel, plan, q_offset_rad: np.ndarray | None = None, **variants) -> np.ndarray:
        v = model.values()
        out = np.zeros((len(plan.starts), len(plan.sample_offsets), STATE_SIZE))
        out[..., 6] = 1.0
        start = self.data.q_rad[plan.starts] - (0.0 if q_offset_rad is None else q_offset_rad)
        out[..., 13:25] = self.data.q_rad[plan.starts][:, None, :]
        s = plan.starts[:, None, None].astype(float)
        k = plan.sample_offsets[None, :, None].astype(float)
        p1 = np.sin(0.013 * s + 0.31 * k + 0.9 * np.arange(12)[None, None, :])
        out[..., 25:37] = 2.0 * start[:, None, :] + 0.14 * v["joint_viscous_friction_nms_per_rad"] * p1
        return out


def test_an_encoder_offset_on_one_knee_is_named_for_that_joint() -> None:
    data = _stand_in_data()
    offset = np.zeros(12)
    offset[8] = 0.05
    true_q = data.q_rad.copy()
    data.q_rad += offset  # the encoder reads the true angle plus the offset
    data.qd_rad_s = 2.0 * true_q + np.random.default_rng(4).normal(0.0, 0.02, true_q.shape)
    sim = _EncoderStandIn(data)
    windows = {"identification": (1.0, 4.5), "holdout": (4.5, 6.0)}
    candidates = [CANDIDATES_BY_NAME["joint_viscous_friction"]]
    result, findings, _ = _dynamics_with(sim, data, candidates, SimModel.nominal(), windows, Settings())
    named = {f.label: f.values for f in findings if f.status == "named"}
    assert list(named) == ["encoder_offset[j8]"], result.verdict
    assert named["encoder_offset[j8]"]["encoder_offset_j8_rad"] == pytest.approx(0.05, rel=0.05)
    assert result.named == ("encoder_offset[j8]",) and not result.remainder.flagged


def test_the_benchmark_scores_a_one_leg_sensor_gain_and_a_knee_offset_as_in_library_variants() -> None:
    def label(kind: str, values: dict, leg: str, joint: str) -> dict:
        effect = {"kind": kind, "values": values, "detectable": True, "out_of_library": True, "leg": leg}
        return {"name": "outlib_00", "effects": [{**effect, "joint": joint}]}  # an older label's flag: ignored

    gain = label("leg_torque_sensor_gain", {"leg_torque_sensor_gain": 0.85, "leg": 1.0}, "RF", "")
    knee = label("encoder_offset", {"encoder_offset_rad": 0.05, "joint": 8.0}, "LH", "lh_kfe_joint")
    right = {**_outcome({"leg_torque_sensor_gain": {"torque_sensor_gain_rf": 0.84}}, False), "where": {}}
    right["where"] = {"leg_torque_sensor_gain": "RF"}
    wrong_leg = {**right, "where": {"leg_torque_sensor_gain": "LF"}}
    global_gain = _outcome({"torque_gain": {"torque_gain": 0.96}}, False)
    offset = {
        **_outcome({"encoder_offset": {"encoder_offset_lh_kfe_joint_rad": 0.049}}, False),
        "where": {"encoder_offset": "lh_kfe_joint"},
    }
    rows = [score(right, gain), score(wrong_leg, gain), score(global_gain, gain), score(offset, knee)]
    assert [r["variant_named_where"] for r in rows] == [
        {"leg_torque_sensor_gain": True},
        {"leg_torque_sensor_gain": False},
        {"leg_torque_sensor_gain": False},
        {"encoder_offset": True},
    ]
    assert rows[0]["param_errors"]["leg_torque_sensor_gain"] == pytest.approx(0.01 / 0.85)
    assert rows[3]["param_errors"]["encoder_offset"] == pytest.approx(0.02)
    assert rows[0]["named"] == ["leg_torque_sensor_gain[RF]"] and not rows[0]["out_of_library"]
    table = {row[0]: row for row in acceptance(rows)}
    key = next(k for k in table if k.startswith("per-leg / per-joint effects named"))
    assert table[key][1].startswith("2/4") and not table[key][3]
