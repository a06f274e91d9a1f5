"""VPA: pose evaluation, RBF fit, hip-height geometry, optimiser, PoseAdapter statuses, TBR and the CNN."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from tal_lab.vital.terrain_samples import random_terrain
from tal_lab.vital.vpa_dataset import TROT_GAIT
from tal_lab.vital.vpa_scenes import SCENE_KINDS, vpa_scenes

from tal_core.heightmap import HeightMapGrid, extract_heightmap
from tal_core.legs import LEGS, Leg
from tal_core.robot_model import RobotModel
from tal_core.rotations import quat_xyzw_from_rotation
from tal_core.terrain import load_course
from tal_perception import vpa_evaluation
from tal_perception.errors import PerceptionInputError, VpaConfigError, VpaModelError
from tal_perception.fec import FootholdEvaluator
from tal_perception.fec_grid import erode
from tal_perception.fec_settings import FecSettings, GaitTiming
from tal_perception.rbf import RbfBasis
from tal_perception.tbr import TerrainBasedReference
from tal_perception.vfa import extract_patch
from tal_perception.vpa import PoseAdapter, VpaStatus
from tal_perception.vpa_evaluation import PoseEvaluator
from tal_perception.vpa_optimizer import HipHeightModel, PoseOptimizer, PoseProblem, Solver
from tal_perception.vpa_settings import CostKind, VpaSettings

SETTINGS = VpaSettings()
HEIGHTS = SETTINGS.hip_heights
WALK = np.array([0.3, 0.0, 0.0, 0.0, 0.0, 0.0])
STILL = np.zeros(6)


@pytest.fixture(scope="module")
def pose_evaluator(evaluator: FootholdEvaluator) -> PoseEvaluator:
    return PoseEvaluator(evaluator, HEIGHTS)


@pytest.fixture(scope="module")
def basis() -> RbfBasis:
    return RbfBasis(HEIGHTS, SETTINGS.rbf_count, SETTINGS.rbf_intersection)


def flat_grid(height: float = 0.0, cells: int = 141) -> HeightMapGrid:
    return HeightMapGrid((0.0, 0.0), 0.0, 0.02, np.full((cells, cells), height, dtype=np.float32))


def rotation(roll: float, pitch: float) -> np.ndarray:
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    r_x = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    r_y = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    return r_y @ r_x


# -- settings and RBF ------------------------------------------------------------------------------------
def test_settings_give_the_thesis_grid_and_reject_bad_values() -> None:
    assert HEIGHTS.size == 31 and HEIGHTS[0] == pytest.approx(0.2) and HEIGHTS[-1] == pytest.approx(0.8)
    with pytest.raises(VpaConfigError, match="rbf_count"):
        VpaSettings(rbf_count=0)
    with pytest.raises(VpaConfigError, match="pose_lower"):
        VpaSettings(pose_lower=(0.9, -0.35, -0.35))
    with pytest.raises(VpaConfigError, match="max_map_age_s"):
        VpaSettings(max_map_age_s=0.0)
    assert (SETTINGS.swing_hip_model, SETTINGS.leg_weighting) == ("level", "none")  # the thesis' by default
    with pytest.raises(VpaConfigError, match=r"VpaSettings.swing_hip_model must be one of \('level', 'terrain'\), "
                       r"got 'flat'"):
        VpaSettings(swing_hip_model="flat")
    with pytest.raises(VpaConfigError, match=r"VpaSettings.leg_weighting must be one of \('none', 'peak'\)"):
        VpaSettings(leg_weighting="max")
    with pytest.raises(VpaConfigError, match=r"VpaSettings.leg_weight_floor must be in \(0, 1\], got 0.0"):
        VpaSettings(leg_weight_floor=0.0)


def test_rbf_fit_reproduces_a_curve_in_its_span_and_a_smooth_bump(basis: RbfBasis) -> None:
    true_weights = np.random.default_rng(0).uniform(0.0, 1.0, basis.count)
    np.testing.assert_allclose(basis.fit(basis.evaluate(true_weights, HEIGHTS)), true_weights, atol=1e-9)
    bump = np.exp(-0.5 * ((HEIGHTS - 0.6) / 0.08) ** 2)  # smooth NSF-like curve, peak 1
    fitted = basis.evaluate(basis.fit(bump), HEIGHTS)
    assert np.abs(fitted - bump).max() < 0.01
    between = np.linspace(0.25, 0.75, 201)  # continuous between the samples as well
    assert np.abs(basis.evaluate(basis.fit(bump), between) - np.exp(-0.5 * ((between - 0.6) / 0.08) ** 2)).max() < 0.02
    z = np.array([0.43])
    numeric = (basis.evaluate(basis.fit(bump), z + 1e-6) - basis.evaluate(basis.fit(bump), z - 1e-6)) / 2e-6
    assert basis.slope(basis.fit(bump), z) == pytest.approx(numeric, rel=1e-5)


# -- hip heights from the pose --------------------------------------------------------------------------
def test_hip_heights_match_the_robot_model(hyq: RobotModel) -> None:
    hips = HipHeightModel.from_model(hyq)
    rng = np.random.default_rng(1)
    model = RobotModel(hyq.description)  # private copy: the session model's cache stays untouched
    for _ in range(5):
        z_b, roll, pitch = rng.uniform(0.3, 0.8), rng.uniform(-0.35, 0.35), rng.uniform(-0.35, 0.35)
        quat = quat_xyzw_from_rotation(rotation(roll, pitch))
        q = model.make_q([0.1, -0.2, z_b], quat, hyq.description.nominal_joint_positions_rad)
        model.update(q, np.zeros(model.nv))
        np.testing.assert_allclose(hips.heights([z_b, roll, pitch]), model.hip_positions()[:, 2], atol=1e-12)
        u = np.array([z_b, roll, pitch])
        numeric = np.stack(
            [(hips.heights(u + e) - hips.heights(u - e)) / 2e-7 for e in np.eye(3) * 1e-7], axis=1
        )
        np.testing.assert_allclose(hips.jacobian(u), numeric, atol=1e-6)


# -- exact pose evaluation --------------------------------------------------------------------------------
@pytest.mark.parametrize(("kind", "leg", "twist"), [
    ("bars", Leg.LF, [0.3, 0.05, 0, 0, 0, 0.2]), ("stairs", Leg.RH, [0.2, 0, 0, 0, 0, -0.3]),
    ("rocks", Leg.LH, [0.0, -0.1, 0, 0, 0, 0.0]),
])  # fmt: skip
def test_shared_evaluation_equals_the_fec_at_every_height(
    pose_evaluator: PoseEvaluator, kind: str, leg: Leg, twist: list[float]
) -> None:
    heights = random_terrain(np.random.default_rng(7), kind).heights.astype(float)
    fast = pose_evaluator.evaluate(leg, heights, np.array(twist, dtype=float), TROT_GAIT).nsf
    reference = pose_evaluator.reference_counts(leg, heights, np.array(twist, dtype=float), TROT_GAIT)
    np.testing.assert_array_equal(fast, reference)
    assert fast.max() > 0


@pytest.mark.parametrize(("seed", "legs"), [(3, (Leg.LF, Leg.RH)), (4, (Leg.RF, Leg.LH))])
def test_shared_evaluation_equals_the_fec_on_whole_robot_scene_maps(
    hyq: RobotModel, evaluator: FootholdEvaluator, pose_evaluator: PoseEvaluator, seed: int, legs: tuple[Leg, ...]
) -> None:
    """The leg maps the VPA really evaluates (bench scenes: both horizon stages, yawed, turning): the
    shortcuts of the shared evaluation (dropped heights, joint origins of feasible legs only, segment
    ends before the terrain look-up) give exactly the FEC's count at every height."""
    adapter = PoseAdapter(RobotModel(hyq.description), evaluator=evaluator)
    fec = evaluator.settings
    rng = np.random.default_rng(seed)
    total = 0
    for scene in vpa_scenes(seed, len(SCENE_KINDS), hyq.nominal_base_height_m):
        if scene.kind == "flat":
            continue
        yaw = float(rng.uniform(-0.5, 0.5))
        centres, _ = adapter.map_centres(scene.base_position, yaw, scene.twist)
        stage = int(rng.integers(centres.shape[0]))
        for leg in legs:
            heights = extract_patch(scene.grid, centres[stage, leg], yaw, fec.patch_cells, fec.resolution_m)
            fast = pose_evaluator.evaluate(leg, heights, scene.twist, TROT_GAIT).nsf
            np.testing.assert_array_equal(fast, pose_evaluator.reference_counts(leg, heights, scene.twist, TROT_GAIT))
            total += int(fast.sum())
    assert total > 0


@pytest.mark.parametrize(("kind", "leg", "twist"), [
    ("stairs", Leg.LF, [0.3, 0, 0, 0, 0, 0]), ("stairs", Leg.RH, [0.3, 0.05, 0, 0, 0, 0.2]),
    ("bars", Leg.LH, [0.4, 0, 0, 0, 0, -0.3]), ("gaps", Leg.RF, [0.2, 0, 0, 0, 0, 0]),
])  # fmt: skip
def test_terrain_swing_model_evaluation_equals_the_fec_at_every_height(
    evaluator: FootholdEvaluator, kind: str, leg: Leg, twist: list[float]
) -> None:
    """With the hip following the terrain during the swing, the shared evaluation still gives exactly the
    FEC's count at every height (the FEC with ``hip_rise_at_liftoff_m``, ``reference_counts``), and it
    differs from the level model on some of these maps (the lift-off lies on another level)."""
    terrain = PoseEvaluator(evaluator, HEIGHTS, "terrain")
    changed = 0
    for seed in range(3):
        heights = random_terrain(np.random.default_rng(seed), kind).heights.astype(float)
        fast = terrain.evaluate(leg, heights, np.array(twist, dtype=float), TROT_GAIT).nsf
        np.testing.assert_array_equal(fast, terrain.reference_counts(leg, heights, np.array(twist, dtype=float),
                                                                     TROT_GAIT))
        level = PoseEvaluator(evaluator, HEIGHTS).evaluate(leg, heights, np.array(twist, dtype=float), TROT_GAIT).nsf
        changed += int(not np.array_equal(fast, level))
    assert changed > 0
    with pytest.raises(VpaConfigError, match=r"swing_hip_model must be one of \('level', 'terrain'\), got 'up'"):
        PoseEvaluator(evaluator, HEIGHTS, "up")


def test_terrain_swing_model_keeps_the_front_legs_footholds_at_the_top_of_the_flight(hyq: RobotModel) -> None:
    """The stairs course at 0.5 m/s (1.8 Hz), base at x = 2.8 m on the top landing, the front hips over the
    first tread down. The level model evaluates the front legs' lift-off (still on the landing, behind the
    hips) at the touchdown height and finds their safe footholds only where the lower tread is barely in
    reach: the VPA's pose leaves them 16 each (1089 cells). Following the terrain it finds 137 each, the hind
    legs keep theirs."""
    course = load_course("vital_stairs")
    grid = extract_heightmap(course, (2.8, 0.0), 0.0, rows=81, cols=81, resolution_m=0.02)
    found = {}
    for model in ("level", "terrain"):
        adapter = PoseAdapter(RobotModel(hyq.description), dataclasses.replace(SETTINGS, swing_hip_model=model))
        for _ in range(6):  # from the default pose, within the change bound per update
            result = adapter.update(grid, np.array([2.8, 0.0, 1.04]), 0.0, np.array([0.5, 0, 0, 0, 0, 0]),
                                    GaitTiming(1.8, 0.6, 0.0, 0.1))
        found[model] = result.safe_footholds
    assert (found["level"][:2] < 20).all() and (found["terrain"][:2] > 100).all()
    assert (found["terrain"][2:] >= 700).all()


def test_peak_leg_weighting_scales_every_curve_to_its_peak(hyq: RobotModel, basis: RbfBasis) -> None:
    """"peak": every (stage, leg) curve divided by its peak over the sampled heights (floored), so a leg with
    few safe footholds weighs in the optimiser like one with many; the pose then serves it better."""
    settings = dataclasses.replace(SETTINGS, leg_weighting="peak", leg_weight_floor=0.05)
    adapter = PoseAdapter(RobotModel(hyq.description), settings)
    bump = np.exp(-0.5 * ((HEIGHTS - 0.62) / 0.03) ** 2)
    high = np.exp(-0.5 * ((HEIGHTS - 0.52) / 0.05) ** 2)
    curves = np.stack([0.08 * bump, 0.08 * bump, 0.6 * high, 0.01 * high])[None]  # (1, 4, N): RH below the floor
    weights = basis.fit(curves)
    scaled = basis.evaluate(adapter._weighted(weights)[:, :, None, :], HEIGHTS[None, None, :])
    np.testing.assert_allclose(scaled.max(axis=-1)[0, :3], 1.0, rtol=1e-12)
    peak = basis.evaluate(weights[:, :, None, :], HEIGHTS[None, None, :]).max(axis=-1)[0, 3]
    assert scaled.max(axis=-1)[0, 3] == pytest.approx(peak / 0.05, rel=1e-12)
    symmetric = basis.fit(np.stack([0.08 * bump, 0.08 * bump, 0.6 * high, 0.6 * high])[None])  # front legs: few
    problem = PoseProblem(symmetric, np.zeros((1, 4)), np.array([0.55, 0.0, 0.0]))
    plain = adapter.optimizer.solve(problem)
    weighted = adapter.optimizer.solve(PoseProblem(adapter._weighted(symmetric), problem.offsets, problem.previous))
    front = [basis.evaluate(symmetric[0, :2], adapter.hips.heights(s.poses[0])[:2]) for s in (plain, weighted)]
    assert (front[1] > 1.2 * front[0]).all(), front
    unweighted = PoseAdapter(RobotModel(hyq.description), SETTINGS)
    assert unweighted._weighted(weights) is weights


def test_the_cnn_evaluation_refuses_the_terrain_swing_model(hyq: RobotModel) -> None:
    from tal_perception.vpa_cnn import CnnNsfModel

    with pytest.raises(VpaConfigError, match=r"swing_hip_model 'terrain' needs the exact evaluation"):
        PoseAdapter(RobotModel(hyq.description), dataclasses.replace(SETTINGS, swing_hip_model="terrain"),
                    nsf_model=CnnNsfModel.load())


@pytest.mark.parametrize("block", [1, 37, 1089])
def test_pair_blocks_give_the_same_counts(
    pose_evaluator: PoseEvaluator, monkeypatch: pytest.MonkeyPatch, block: int
) -> None:
    """The IK / LC batches are made of whole layers of at most ``_BLOCK_PAIRS`` pairs (a layer alone if it
    holds more): any block size gives the counts of one batch per instant, i.e. the FEC's."""
    cases = [("stairs", Leg.RF, [0.3, 0.0, 0, 0, 0, 0.1]), ("bars", Leg.LH, [0.2, 0.05, 0, 0, 0, -0.2])]
    maps = [(random_terrain(np.random.default_rng(11), kind).heights.astype(float), leg, np.array(twist, dtype=float))
            for kind, leg, twist in cases]  # fmt: skip
    one_batch = [pose_evaluator.evaluate(leg, heights, twist, TROT_GAIT).nsf for heights, leg, twist in maps]
    monkeypatch.setattr(vpa_evaluation, "_BLOCK_PAIRS", block)
    for (heights, leg, twist), expected in zip(maps, one_batch):
        blocked = pose_evaluator.evaluate(leg, heights, twist, TROT_GAIT).nsf
        np.testing.assert_array_equal(blocked, expected)
        np.testing.assert_array_equal(blocked, pose_evaluator.reference_counts(leg, heights, twist, TROT_GAIT))
        assert blocked.max() > 0


@pytest.mark.parametrize("margin_m", [0.0, 0.02, 0.05])
def test_stack_erosion_and_dilation_equal_the_fec_erosion_per_layer(hyq: RobotModel, margin_m: float) -> None:
    """The stack morphology (flattened shifts, side edges masked) equals fec_grid.erode on every layer, and
    dilation is its dual (outside the patch: safe for the erosion, nothing for the dilation)."""
    evaluator = FootholdEvaluator(hyq, FecSettings(uncertainty_margin_m=margin_m))
    stacked = PoseEvaluator(evaluator, HEIGHTS)
    stack = np.random.default_rng(5).uniform(size=(6, 33, 33)) < 0.85
    eroded, dilated = stacked._erode(stack), stacked._dilate(stack)
    for layer in range(stack.shape[0]):
        np.testing.assert_array_equal(eroded[layer], erode(stack[layer], 0.02, margin_m))
        np.testing.assert_array_equal(dilated[layer], ~erode(~stack[layer], 0.02, margin_m))
    assert stacked._erode(stack[:0]).shape == (0, 33, 33)


def test_layer_blocks_cover_the_stack_in_order_within_the_limit() -> None:
    counts = np.array([2, 2, 5, 1, 0, 3, 1])
    blocks = vpa_evaluation._layer_blocks(counts, 4)
    assert blocks == [slice(0, 2), slice(2, 3), slice(3, 6), slice(6, 7)]  # the 5 (> 4) forms a block alone
    assert vpa_evaluation._layer_blocks(np.array([7]), 4) == [slice(0, 1)]


def test_unknown_cells_are_unsafe(pose_evaluator: PoseEvaluator) -> None:
    flat = np.zeros((33, 33))
    partly = flat.copy()
    partly[:, :12] = np.nan
    full = pose_evaluator.evaluate(Leg.LF, flat, WALK, TROT_GAIT).nsf
    occluded = pose_evaluator.evaluate(Leg.LF, partly, WALK, TROT_GAIT).nsf
    assert full.max() > 0 and (occluded <= full).all() and occluded.sum() < full.sum()
    # the known part is 33 x 21 cells; one column next to the unknown ones is eroded away
    assert occluded.max() <= 33 * 20
    unknown = pose_evaluator.evaluate(Leg.LF, np.full((33, 33), np.nan), WALK, TROT_GAIT)
    assert not unknown.nsf.any() and math.isnan(unknown.reference_m)


def test_wrong_map_size_and_nan_twist_raise(pose_evaluator: PoseEvaluator) -> None:
    with pytest.raises(PerceptionInputError, match="patch shape"):
        pose_evaluator.evaluate(Leg.LF, np.zeros((21, 21)), WALK, TROT_GAIT)
    with pytest.raises(PerceptionInputError, match="twist has non-finite"):
        pose_evaluator.evaluate(Leg.LF, np.zeros((33, 33)), np.array([np.nan, 0, 0, 0, 0, 0]), TROT_GAIT)


# -- optimiser -------------------------------------------------------------------------------------------
def synthetic_problem(rng: np.random.Generator, basis: RbfBasis, stages: int = 2) -> PoseProblem:
    """NSF-like bumps (peak 0.3-0.9 of the cells) at random heights per stage and leg."""
    peaks = rng.uniform(0.4, 0.7, (stages, 4, 1))
    widths = rng.uniform(0.04, 0.1, (stages, 4, 1))
    curves = rng.uniform(0.3, 0.9, (stages, 4, 1)) * np.exp(-0.5 * ((HEIGHTS - peaks) / widths) ** 2)
    previous = np.array([rng.uniform(0.4, 0.7), rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1)])
    return PoseProblem(basis.fit(curves), rng.uniform(-0.05, 0.05, (stages, 4)), previous)


@pytest.mark.parametrize("cost", list(CostKind), ids=lambda c: c.value)
def test_optimiser_respects_bounds_and_agrees_with_trust_constr(
    hyq: RobotModel, basis: RbfBasis, cost: CostKind
) -> None:
    settings = dataclasses.replace(SETTINGS, cost=cost)
    optimizer = PoseOptimizer(settings, basis, HipHeightModel.from_model(RobotModel(hyq.description)))
    rng = np.random.default_rng(11)
    change = np.array(settings.max_change)
    for _ in range(4):
        problem = synthetic_problem(rng, basis)
        x0 = optimizer.initial_guess(problem)
        fast = optimizer.solve(problem, Solver.LBFGSB, x0=x0)
        reference = optimizer.solve(problem, Solver.TRUST_CONSTR, x0=x0)
        for stage, pose in enumerate(fast.poses, start=1):
            assert (pose >= np.array(settings.pose_lower) - 1e-12).all()
            assert (pose <= np.array(settings.pose_upper) + 1e-12).all()
            assert (np.abs(pose - problem.previous) <= stage * change + 1e-12).all()
        same_pose = np.abs(fast.poses - reference.poses).max() <= 1e-3
        same_value = abs(fast.objective - reference.objective) <= 1e-6 * max(abs(reference.objective), 1e-12)
        assert same_pose or same_value, (fast.poses, reference.poses, fast.objective, reference.objective)


# -- PoseAdapter -----------------------------------------------------------------------------------------
def test_a_second_start_finds_the_nose_up_pose_a_flat_objective_hides(hyq: RobotModel, evaluator: FootholdEvaluator
                                                                       ) -> None:
    """The stairs course at 0.4 m/s, base at x = 0.78 m, the front hips over the first tread: the front
    legs have safe footholds only 0.56-0.64 m above their tread (a narrow curve), none at the level
    start poses. From those the front legs give (almost) no gradient and a single start settles for
    the hind legs; the second start (``peak_pose``) pitches nose up and serves all four legs."""
    course = load_course("vital_stairs")
    adapter = PoseAdapter(RobotModel(hyq.description), SETTINGS)
    grid = extract_heightmap(course, (0.78, 0.0), 0.0, rows=81, cols=81, resolution_m=0.02)
    result = adapter.update(grid, np.array([0.78, 0.0, 0.66]), 0.0, np.array([0.4, 0, 0, 0, 0, 0]),
                            GaitTiming(1.5, 0.6, 0.0, 0.1))
    assert result.status is VpaStatus.OK
    assert result.safe_footholds[0] > 50 and result.safe_footholds[1] > 50  # front legs served
    assert math.degrees(result.pitch_rad) < -3.0  # nose up
    d = result.diagnostics
    problem = PoseProblem(d.weights, d.body_reference_m - d.map_references, adapter.default_relative)
    optimizer = adapter.optimizer
    single = optimizer.solve(problem, Solver.LBFGSB, x0=optimizer.initial_guess(problem))
    both = optimizer.solve(problem, Solver.LBFGSB)
    front = [adapter.basis.evaluate(d.weights[0, :2], (optimizer.hips.heights(s.poses) + problem.offsets)[0, :2])
             for s in (single, both)]
    assert np.all(front[0] < 0.25 * front[1])  # the single start all but leaves the front legs out
    assert both.objective > single.objective


@pytest.fixture(scope="module")
def adapter(hyq: RobotModel, evaluator: FootholdEvaluator) -> PoseAdapter:
    return PoseAdapter(RobotModel(hyq.description), evaluator=evaluator)


def test_flat_ground_gives_the_level_maximal_nsf_pose(hyq: RobotModel, evaluator: FootholdEvaluator) -> None:
    free = dataclasses.replace(SETTINGS, max_change=(0.6, 0.7, 0.7))  # reach the optimum in one update
    vpa = PoseAdapter(RobotModel(hyq.description), free, evaluator=evaluator)
    result = vpa.update(flat_grid(0.1), [0.0, 0.0, 0.7], 0.3, STILL, TROT_GAIT)
    assert result.status is VpaStatus.OK and result.optimal
    assert abs(result.roll_rad) < 1e-3 and abs(result.pitch_rad) < 1e-3
    samples = result.diagnostics.nsf_samples[0]  # (4, 31), all legs alike on flat ground
    best = HEIGHTS[np.argmax(samples.sum(axis=0))]
    assert abs(result.base_height_m - 0.1 - best) <= 0.03  # hips at z = 0 in the base frame (HyQ)
    assert (result.safe_footholds >= 0.9 * samples.max(axis=1)).all()
    np.testing.assert_allclose(result.hip_heights_m, result.base_height_m, atol=1e-3)


def test_receding_horizon_maps_are_shifted_half_a_diagonal_along_the_velocity(adapter: PoseAdapter) -> None:
    twist = np.array([0.3, 0.3, 0.0, 0.0, 0.0, 0.0])
    centres, horizon_s = adapter.map_centres(np.array([1.0, 2.0, 0.6]), 0.5, twist)
    shift = centres[1] - centres[0]
    diagonal = math.sqrt(2.0) * 33 * 0.02
    np.testing.assert_allclose(np.linalg.norm(shift, axis=1), 0.5 * diagonal)
    c, s = math.cos(0.5), math.sin(0.5)
    direction = np.array([c * 0.3 - s * 0.3, s * 0.3 + c * 0.3]) / math.hypot(0.3, 0.3)
    np.testing.assert_allclose(shift / np.linalg.norm(shift, axis=1, keepdims=True), np.tile(direction, (4, 1)))
    assert horizon_s == pytest.approx(0.5 * diagonal / math.hypot(0.3, 0.3))
    standing, standing_s = adapter.map_centres(np.array([1.0, 2.0, 0.6]), 0.5, STILL)
    np.testing.assert_allclose(standing[1], standing[0])
    assert standing_s == 0.0


def test_missing_or_stale_map_holds_the_default_pose(hyq: RobotModel, evaluator: FootholdEvaluator) -> None:
    vpa = PoseAdapter(RobotModel(hyq.description), evaluator=evaluator)
    no_map = vpa.update(None, [0.0, 0.0, 0.62], 0.0, WALK, TROT_GAIT)
    assert no_map.status is VpaStatus.NO_MAP and not no_map.optimal
    assert no_map.base_height_m == pytest.approx(0.62) and no_map.roll_rad == 0.0 and no_map.pitch_rad == 0.0
    first = vpa.update(flat_grid(0.2), [0.0, 0.0, 0.8], 0.0, STILL, TROT_GAIT)
    assert first.status is VpaStatus.OK
    # the change per update is bounded: from the held pose by at most max_change
    assert abs(first.base_height_m - no_map.base_height_m) <= SETTINGS.max_change[0] + 1e-9
    stale = vpa.update(flat_grid(0.2), [0.0, 0.0, 0.8], 0.0, STILL, TROT_GAIT, map_age_s=2.0)
    assert stale.status is VpaStatus.STALE_MAP and not stale.optimal
    assert stale.base_height_m == pytest.approx(0.2 + hyq.nominal_base_height_m)  # nominal above the terrain
    assert stale.roll_rad == 0.0 and stale.pitch_rad == 0.0


def test_unknown_map_holds_a_pose_flagged(hyq: RobotModel, evaluator: FootholdEvaluator) -> None:
    vpa = PoseAdapter(RobotModel(hyq.description), evaluator=evaluator)
    unknown = HeightMapGrid((0.0, 0.0), 0.0, 0.02, np.full((141, 141), np.nan, dtype=np.float32))
    result = vpa.update(unknown, [0.0, 0.0, 0.6], 0.0, STILL, TROT_GAIT)
    assert result.status is VpaStatus.NO_SAFE_FOOTHOLD and not result.optimal
    assert not result.safe_footholds.any()


def test_bad_inputs_raise_precise_errors(adapter: PoseAdapter) -> None:
    grid = flat_grid()
    with pytest.raises(PerceptionInputError, match=r"twist must have shape \(6,\)"):
        adapter.update(grid, [0, 0, 0.6], 0.0, [0.3, 0.0, 0.0], TROT_GAIT)
    with pytest.raises(PerceptionInputError, match="twist has non-finite value"):
        adapter.update(grid, [0, 0, 0.6], 0.0, [np.nan, 0, 0, 0, 0, 0], TROT_GAIT)
    with pytest.raises(PerceptionInputError, match="base_position has non-finite"):
        adapter.update(grid, [0, np.inf, 0.6], 0.0, WALK, TROT_GAIT)
    with pytest.raises(PerceptionInputError, match="in the future"):
        adapter.update(grid, [0, 0, 0.6], 0.0, WALK, TROT_GAIT, map_age_s=-0.5)
    with pytest.raises(PerceptionInputError, match="yaw must be a finite"):
        adapter.update(grid, [0, 0, 0.6], float("nan"), WALK, TROT_GAIT)
    with pytest.raises(PerceptionInputError, match="gait must be a GaitTiming"):
        adapter.update(grid, [0, 0, 0.6], 0.0, WALK, "trot")  # type: ignore[arg-type]


# -- TBR -------------------------------------------------------------------------------------------------
def test_tbr_plane_through_known_footholds() -> None:
    slope_x, slope_y, yaw = 0.2, -0.1, 0.4
    c, s = math.cos(yaw), math.sin(yaw)
    local = np.array([[0.4, 0.3], [0.4, -0.3], [-0.4, 0.3], [-0.4, -0.3]])  # horizontal frame
    world_xy = local @ np.array([[c, s], [-s, c]]) + np.array([2.0, 1.0])
    footholds = np.column_stack([world_xy, 0.5 + slope_x * local[:, 0] + slope_y * local[:, 1]])
    result = TerrainBasedReference(0.55).reference(footholds, yaw)
    np.testing.assert_allclose(result.plane_slopes, [slope_x, slope_y], atol=1e-12)
    body_z = rotation(result.roll_rad, result.pitch_rad)[:, 2]  # horizontal frame
    normal = np.array([-slope_x, -slope_y, 1.0]) / math.sqrt(1.0 + slope_x**2 + slope_y**2)
    np.testing.assert_allclose(body_z, normal, atol=1e-12)
    assert result.base_height_m == pytest.approx(0.5 + 0.55 * normal[2])
    with pytest.raises(PerceptionInputError, match="collinear"):
        TerrainBasedReference(0.55).reference([[0, 0, 0], [1, 0, 0], [2, 0, 0]], 0.0)
    with pytest.raises(PerceptionInputError, match="shape"):
        TerrainBasedReference(0.55).reference([[0, 0, 0], [1, 0, 0]], 0.0)
    with pytest.raises(VpaConfigError, match="height_m"):
        TerrainBasedReference(-1.0)


# -- CNN -------------------------------------------------------------------------------------------------
def test_committed_cnn_weights_load_and_approximate_fresh_curves(pose_evaluator: PoseEvaluator, basis: RbfBasis) -> None:
    pytest.importorskip("torch")
    from tal_lab.vital.vpa_dataset import generate

    from tal_perception.vpa_cnn import CnnNsfModel

    model = CnnNsfModel.load()
    model.check(SETTINGS.rbf_count, 33)
    data = generate(seed=424242, count=40, evaluator=pose_evaluator, progress=False)
    weights, _ = model.predict([LEGS[i] for i in data.legs], data.heights.astype(float), data.twists)
    f_hat = basis.evaluate(weights[:, None, :], HEIGHTS[None, :]) * 33 * 33
    f_bar = data.nsf.astype(float)
    assert 0.9 <= f_hat.mean() / f_bar.mean() <= 1.1
    assert 1.0 - np.abs(f_hat - f_bar).mean() / f_bar.mean() >= 0.6  # measured 0.72 here, 0.75 on 1000 maps
    with pytest.raises(VpaModelError, match="E = 30"):
        model.check(12, 33)


def test_missing_weights_file_raises(tmp_path) -> None:
    pytest.importorskip("torch")
    from tal_perception.vpa_cnn import CnnNsfModel

    with pytest.raises(VpaModelError, match="not found"):
        CnnNsfModel.load(tmp_path / "nothing.pt")
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"not a torch file")
    with pytest.raises(VpaModelError, match="corrupt"):
        CnnNsfModel.load(corrupt)
