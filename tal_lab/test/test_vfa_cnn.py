"""VFA CNN: dataset determinism and labels, encoding, network shapes, selector interface, committed weights."""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np
import pytest
import torch
from tal_lab.vital.tune_vfa_decode import network_outputs
from tal_lab.vital.vfa_dataset import (
    HIP_RANGES,
    VfaDataset,
    cache_path,
    canonical_legs,
    closest_safe_index,
    generate,
    load_or_generate,
    mirrored,
    set_prefix,
)

from tal_core.heightmap import HeightMapGrid, extract_heightmap
from tal_core.legs import LEGS, Leg
from tal_core.terrain import Course, DefaultGround, GapPatch, Region
from tal_perception.errors import FecConfigError, PerceptionInputError
from tal_perception.fec import FootholdEvaluator
from tal_perception.fec_settings import FecInput, GaitTiming
from tal_perception.vfa import FootholdSelector, VfaResult, VfaStatus, extract_patch
from tal_perception.vfa_cnn import (
    DEFAULT_WEIGHTS,
    CnnFootholdSelector,
    EncodingConfig,
    FootholdRequest,
    NetConfig,
    RoughnessFeatures,
    VfaNet,
    VfaUNet,
    _row_medians,
    build_net,
    canonical_inputs,
    encode,
    load_model,
    mirror_cell_index,
    mirror_cell_maps,
    save_model,
)
from tal_perception.vfa_cnn_fast import compile_fast_unet
from tal_perception.vfa_decode import VfaDecode
from tal_perception.vfa_decode import decode as decode_choices

TROT_SWING = GaitTiming(step_frequency_hz=1.5, duty_factor=0.6, swing_time_left_s=0.2, step_height_m=0.1)
TWIST = np.array([0.3, 0.0, 0.0, 0.0, 0.0, 0.1])
RIGID = {"stiffness_n_per_m": 2e6, "damping_ns_per_m": 400.0}
NOMINAL = np.array([0.40, 0.21, 0.0])
# Measured on the 4401-per-leg protocol (results/vital/vfa_cnn_accuracy.md, the widened VfaUNet weights
# fine-tuned with the wide hip range, with their stored decode, combined lambda 1.5): perfect match 75.3 %,
# safe 87.8 %, perfect match on the samples that need adaptation 58.5 % (the previous weights: 74.5 / 88.3 /
# 57.6 %). The thresholds sit below (400 samples vary by a few %) and above the
# previous VfaNet weights (64.9 / 75.5 / 39.6 %); the last one fails a network that always keeps the nominal
# (0 % there, while that trivial answer scores ~44 % perfect match overall).
MIN_PERFECT_MATCH = 0.67
MIN_SAFE = 0.81
MIN_PERFECT_MATCH_ADAPTED = 0.46


@pytest.fixture(scope="module")
def cnn_selector(evaluator: FootholdEvaluator) -> CnnFootholdSelector:
    torch.set_num_threads(1)
    return CnnFootholdSelector(evaluator, load_model(DEFAULT_WEIGHTS), verify=False)


@pytest.fixture(scope="module")
def fresh_set(evaluator: FootholdEvaluator) -> VfaDataset:
    """100 fresh tuples per leg (seed 3: neither the training nor the protocol's seed)."""
    return generate(evaluator, seed=3, count=100, progress=False)


def course_map(*patches, size: int = 81) -> HeightMapGrid:
    course = Course("test", Region(-2, 2, -2, 2), DefaultGround(height_m=0.0, **RIGID), tuple(patches))
    return extract_heightmap(course, (NOMINAL[0], NOMINAL[1]), 0.0, size, size, 0.02)


# -- dataset -----------------------------------------------------------------------------------------
def test_dataset_is_deterministic_by_seed_and_independent_of_the_count(evaluator: FootholdEvaluator) -> None:
    a = generate(evaluator, seed=5, count=3, progress=False)
    b = generate(evaluator, seed=5, count=2, progress=False)
    c = generate(evaluator, seed=6, count=2, progress=False)
    assert len(a) == 12 and len(b) == 8
    np.testing.assert_array_equal(a.heights[:8], b.heights)
    np.testing.assert_array_equal(a.label[:8], b.label)
    np.testing.assert_array_equal(a.safe[:8], b.safe)
    assert not np.array_equal(np.nan_to_num(b.heights), np.nan_to_num(c.heights))
    assert list(a.leg[:4]) == [int(leg) for leg in LEGS]


def test_a_smaller_cache_is_extended_to_the_set_of_the_larger_count(evaluator: FootholdEvaluator, tmp_path) -> None:
    full = generate(evaluator, seed=5, count=3, progress=False)
    generate(evaluator, seed=5, count=2, progress=False).save(tmp_path / "train_seed5_n2.npz")
    extended = load_or_generate(evaluator, cache_path(tmp_path, "train", 5, 3), 5, 3)
    assert (tmp_path / "train_seed5_n3.npz").exists() and len(extended) == 12
    for name in ("heights", "hip_height_m", "twist", "gait", "leg", "kind", "safe", "label"):
        np.testing.assert_array_equal(getattr(extended, name), getattr(full, name))
    assert len(load_or_generate(evaluator, cache_path(tmp_path, "train", 5, 2), 5, 2)) == 8  # the smallest that fits


def test_wide_hip_range_samples_its_heights_under_its_own_cache_name(evaluator: FootholdEvaluator, tmp_path) -> None:
    """A "wide" set draws the hip over HIP_RANGES["wide"] above the patch's median (the same terrain, twist and
    gait draws as the standard set of that seed: only the hip differs), caches as train_wide_seed<s>, and a bad
    range name is a precise error."""
    standard = generate(evaluator, seed=5, count=6, progress=False)
    wide = load_or_generate(evaluator, cache_path(tmp_path, set_prefix("train", "wide"), 5, 6), 5, 6,
                            hip_range="wide")
    assert (tmp_path / "train_wide_seed5_n6.npz").exists() and set_prefix("train", "standard") == "train"
    np.testing.assert_array_equal(np.nan_to_num(wide.heights), np.nan_to_num(standard.heights))
    np.testing.assert_array_equal(wide.twist, standard.twist)
    above = {name: d.hip_height_m - np.nanmedian(d.heights.reshape(len(d), -1), axis=1)
             for name, d in (("standard", standard), ("wide", wide))}
    for name, values in above.items():
        low, high = HIP_RANGES[name]
        assert (values >= low - 1e-4).all() and (values <= high + 1e-4).all()
    assert not np.allclose(above["wide"], above["standard"])
    for call in (lambda: set_prefix("test", "tall"), lambda: generate(evaluator, 5, 1, hip_range="tall")):
        with pytest.raises(FecConfigError, match=r"hip_range must be one of \['standard', 'wide'\], got 'tall'"):
            call()


def test_accuracy_by_hip_bin_splits_the_scored_samples(evaluator: FootholdEvaluator) -> None:
    """eval_vfa's per-bin scores cover every scored sample once, and a bin's perfect match is that of its own
    samples (here: the exact labels as choices, so every bin matches perfectly)."""
    from tal_lab.vital.eval_vfa import hip_above_median_m, per_hip_bin, score

    wide = generate(evaluator, seed=5, count=12, progress=False, hip_range="wide")
    choices = np.where(wide.label >= 0, wide.label, 0).astype(np.intp)
    bins = per_hip_bin(wide, choices, 0.02)
    assert sum(m["scored"] for m in bins.values()) == score(wide, choices, 0.02)["scored"] == int((wide.label >= 0).sum())
    assert all(m["perfect_match"] == 1.0 for m in bins.values() if m["scored"])
    above = hip_above_median_m(wide)
    assert set(bins) <= {"0.40-0.52", "0.52-0.66", "0.66-0.80"} and above.min() < 0.52 < 0.66 < above.max()


def test_labels_are_the_exact_vfa_and_survive_saving(evaluator: FootholdEvaluator, tmp_path) -> None:
    data = generate(evaluator, seed=8, count=3, progress=False)
    selector = FootholdSelector(evaluator)
    n = data.cells
    for i in range(len(data)):
        inp = data.fec_input(i)
        grid = HeightMapGrid(center_xy=(0.0, 0.0), yaw=0.0, resolution_m=0.02, heights=data.heights[i])
        exact = selector.select(inp.leg, [0.0, 0.0, 0.0], grid, hip_height_m=inp.hip_height_m, twist=inp.twist,
                                gait=inp.gait, lazy=False)  # fmt: skip
        expected = (
            -1 if exact.offset_cells is None else (exact.offset_cells[0] + n // 2) * n + exact.offset_cells[1] + n // 2
        )
        assert data.label[i] == expected
        assert exact.safe_candidates == int(data.safe[i].sum())
    data.save(tmp_path / "set.npz")
    loaded = VfaDataset.load(tmp_path / "set.npz")
    np.testing.assert_array_equal(loaded.safe, data.safe)
    np.testing.assert_array_equal(loaded.heights, data.heights)
    assert loaded.seed == 8 and loaded.statistics() == data.statistics()


def test_mirrored_samples_are_the_exact_labels_of_the_other_side(evaluator: FootholdEvaluator) -> None:
    data = generate(evaluator, seed=9, count=2, progress=False)
    mirror = mirrored(data)
    for i in range(len(mirror)):
        safe = evaluator.evaluate(mirror.fec_input(i)).safe
        np.testing.assert_array_equal(safe, mirror.safe[i])
        assert mirror.label[i] == closest_safe_index(safe)
    assert [LEGS[k] for k in mirror.leg[:4]] == [Leg.RF, Leg.LF, Leg.RH, Leg.LH]


# -- encoding and network ------------------------------------------------------------------------------
def test_network_shapes_and_size(tmp_path) -> None:
    net = VfaNet(NetConfig())
    image, scalars = torch.zeros(3, 4, 33, 33), torch.zeros(3, EncodingConfig().scalar_count)
    optimum, safe = net(image, scalars)
    assert optimum.shape == (3, 33 * 33) and safe.shape == (3, 33 * 33)
    torch.testing.assert_close(net.optimum_logits(image, scalars), optimum)
    plain = VfaNet(NetConfig(safe_head=False))
    assert plain(image, scalars)[1] is None and plain(image, scalars)[0].shape == (3, 33 * 33)
    save_model(net, tmp_path / "net.pt")
    assert (tmp_path / "net.pt").stat().st_size < 2e6
    assert load_model(tmp_path / "net.pt").config == net.config
    assert DEFAULT_WEIGHTS.stat().st_size < 2e6


def test_row_medians_equal_numpy_median_of_the_known_cells() -> None:
    """encode's batched median (hip above the patch): np.median of each row's known cells, bit for bit."""
    rng = np.random.default_rng(7)
    values = rng.normal(0.0, 0.1, size=(12, 1089)).astype(np.float32)
    values[:, :40] = np.round(values[:, :40], 2)  # repeated values
    unknown = rng.random(values.shape) < rng.choice([0.0, 0.1, 0.6], size=(12, 1))
    unknown[3, 1:] = True  # one known cell
    unknown[4] = True  # none known
    unknown[5, :2] = True  # an even count
    median, has_known = _row_medians(np.where(unknown, np.nan, values).astype(np.float32), unknown)
    assert has_known.tolist() == [i != 4 for i in range(12)]
    expected = [np.median(v[~u]) if (~u).any() else 0.0 for v, u in zip(values, unknown)]
    np.testing.assert_array_equal(median[has_known], np.array(expected, np.float32)[has_known])


def test_encoding_marks_unknown_cells_and_depends_only_on_height_differences() -> None:
    cfg = EncodingConfig()
    rng = np.random.default_rng(0)
    heights = rng.uniform(-0.1, 0.1, size=(2, 33, 33))
    heights[0, 10:14, 3:9] = np.nan
    heights[1] = np.nan  # nothing known
    hip, twist = np.array([0.6, 0.55]), np.zeros((2, 6))
    gait = np.array([[1.5, 0.6, 0.1, 0.1]] * 2)
    image, scalars = encode(cfg, heights, hip, twist, gait, np.array([0, 3]))
    assert np.isfinite(image).all() and np.isfinite(scalars).all()
    np.testing.assert_array_equal(image[:, 1], np.isnan(heights))
    assert (image[0, 0][np.isnan(heights[0])] == 0.0).all()
    shifted, _ = encode(cfg, heights + 0.3, hip + 0.3, twist, gait, np.array([0, 3]))
    np.testing.assert_allclose(shifted, image, atol=1e-5)
    np.testing.assert_array_equal(scalars[:, -4:], [[1, 0, 0, 0], [0, 0, 0, 1]])


# -- roughness features (NetConfig.roughness_features) ----------------------------------------------------
def _slope_reference(heights: np.ndarray, radius_m: float = 0.04, res: float = 0.02) -> dict[str, np.ndarray]:
    """Per cell in float64, over the slopes to the known in-patch neighbours within ``radius_m`` (the FEC's
    definition, ``fec_grid.terrain_roughness``): mean |s|, RMS, std, mean; and whether a neighbour is unknown."""
    from tal_perception.fec_grid import disc_offsets

    n, k = heights.shape[0], 2
    padded = np.pad(heights, k, constant_values=np.nan)
    inside = np.pad(np.ones_like(heights, dtype=bool), k, constant_values=False)
    slopes, near_unknown = [], np.isnan(heights)
    for di, dj in disc_offsets(radius_m, res):
        neighbour = padded[k + di : k + di + n, k + dj : k + dj + n]
        valid = inside[k + di : k + di + n, k + dj : k + dj + n]
        near_unknown = near_unknown | (valid & np.isnan(neighbour))
        slopes.append(np.where(valid, (neighbour - heights) / (res * np.hypot(di, dj)), np.nan))
    s = np.stack(slopes)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # unknown cells: all-NaN slices give NaN, as intended
        mean, mean_sq = np.nanmean(s, axis=0), np.nanmean(s * s, axis=0)
        return {"mean_abs": np.nanmean(np.abs(s), axis=0), "rms": np.sqrt(mean_sq), "mean": mean,
                "std": np.sqrt(np.maximum(mean_sq - mean * mean, 0.0)), "near_unknown": near_unknown}  # fmt: skip


def test_roughness_features_are_the_fec_slope_statistics_and_never_call_a_rough_cell_smooth() -> None:
    """RoughnessFeatures on encoded random terrains (rocks, bars, stairs, gaps, with unknown cells): the std and
    RMS of the slopes and their mean as the float64 reference; 1 exactly where a cell or a neighbour is
    unknown; and "both features <= 1, nothing unknown nearby" implies the FEC's roughness criterion holds
    (RMS >= mean |s|), while every cell the FEC calls smooth has std <= 1."""
    from tal_lab.vital.terrain_samples import random_terrain

    from tal_perception.fec_grid import terrain_roughness

    rng = np.random.default_rng(11)
    cfg = EncodingConfig()
    heights = np.stack([random_terrain(rng, kind).heights for kind in ("rocks", "bars", "stairs", "gaps") * 3])
    heights[::3, 5:11, 20:24] = np.nan
    heights += rng.uniform(-0.2, 0.2, size=(heights.shape[0], 1, 1))  # any ground level
    hip = np.nanmedian(heights.reshape(len(heights), -1), axis=1) + 0.58
    b = len(heights)
    image, _ = encode(cfg, heights, hip, np.zeros((b, 6)), np.tile([1.5, 0.6, 0.1, 0.1], (b, 1)), np.zeros(b, int))
    features = RoughnessFeatures(cfg.cells, cfg.resolution_m, cfg.height_scale_m)(torch.from_numpy(image)).numpy()
    assert features.shape == (b, 4, 33, 33)
    checked = 0
    for i in range(b):
        known = np.where(image[i, 1] > 0.5, np.nan, image[i, 0] * cfg.height_scale_m)  # encode's clipped heights
        ref = _slope_reference(known)
        rough = ref["near_unknown"]
        np.testing.assert_array_equal(features[i, 3], rough.astype(np.float32))
        assert (features[i, :2][:, rough] == 5.0).all() and (features[i, 2][rough] == 0.0).all()
        free = ~rough
        np.testing.assert_allclose(features[i, 0][free], np.clip(ref["rms"][free] / 0.3, 0, 5), atol=0.03)
        np.testing.assert_allclose(features[i, 1][free], np.clip(ref["std"][free] / 0.35, 0, 5), atol=0.03)
        np.testing.assert_allclose(features[i, 2][free], np.clip(ref["mean"][free] / 0.3, -5, 5), atol=0.03)
        tr = terrain_roughness(heights[i], cfg.resolution_m, 0.04, 0.3, 0.35)  # the FEC's criterion
        said_smooth = (features[i, 0] <= 1.0 - 0.03) & (features[i, 1] <= 1.0 - 0.03) & free
        assert not (said_smooth & ~tr).any()
        assert (features[i, 1][tr] <= 1.0 + 0.03).all() and not (tr & rough).any()
        checked += int(said_smooth.sum())
    assert checked > 1000  # the implication is not vacuous


def test_roughness_features_depend_only_on_height_differences() -> None:
    from tal_lab.vital.terrain_samples import random_terrain

    rng = np.random.default_rng(12)
    cfg = EncodingConfig()
    heights = np.stack([random_terrain(rng, "rocks").heights for _ in range(3)])
    heights[1, 4:9, 10:20] = np.nan
    hip, twist, gait, leg = np.full(3, 0.6), np.zeros((3, 6)), np.tile([1.5, 0.6, 0.1, 0.1], (3, 1)), np.arange(3)
    layer = RoughnessFeatures(cfg.cells, cfg.resolution_m, cfg.height_scale_m)
    image, _ = encode(cfg, heights, hip, twist, gait, leg)
    shifted, _ = encode(cfg, heights + 0.25, hip + 0.25, twist, gait, leg)
    # float32 rounding only: the sums of squares are expanded (h_j - h_c)^2 = h_j^2 - 2 h_j h_c + h_c^2 with h up
    # to a few units, ~1e-2 of the limit at most (an absolute-height feature would differ by ~1 here)
    torch.testing.assert_close(layer(torch.from_numpy(shifted)), layer(torch.from_numpy(image)), rtol=0.0, atol=0.04)
    # the layer itself: the same terrain 0.15 m higher relative to the hip (channel 0 + 1.5 units where known)
    raised = image.copy()
    raised[:, 0] += 1.5 * (1.0 - raised[:, 1])
    torch.testing.assert_close(layer(torch.from_numpy(raised)), layer(torch.from_numpy(image)), rtol=0.0, atol=0.04)
    assert float(layer(torch.from_numpy(image))[:, 0].max()) > 1.0  # rocks: some cells rough


def test_roughness_option_saves_loads_and_old_files_load_without_it(tmp_path) -> None:
    """The option is recorded in the file; a file without the key (before the option) loads as a network
    without it, as the committed weights do; the option needs the unet."""
    torch.manual_seed(8)
    net = build_net(NetConfig(architecture="unet", hidden=32, roughness_features=True)).eval()
    assert isinstance(net, VfaUNet) and net.decoders[2].in_channels == 16 + 8 + 4 + 4
    save_model(net, tmp_path / "rough.pt")
    loaded = load_model(tmp_path / "rough.pt")
    assert loaded.config == net.config and loaded.config.roughness_features
    image = torch.zeros(2, 4, 33, 33)
    image[:, 0] = torch.rand(2, 33, 33)
    scalars = torch.zeros(2, EncodingConfig().scalar_count)
    with torch.inference_mode():
        torch.testing.assert_close(loaded(image, scalars)[0], net(image, scalars)[0], rtol=0.0, atol=1e-2)
    plain = build_net(NetConfig(architecture="unet", hidden=32)).eval()
    save_model(plain, tmp_path / "old.pt")
    document = torch.load(tmp_path / "old.pt", weights_only=True)
    del document["net"]["roughness_features"]  # as written before the option existed
    torch.save(document, tmp_path / "old.pt")
    assert load_model(tmp_path / "old.pt").config == plain.config
    committed = load_model(DEFAULT_WEIGHTS)
    assert isinstance(committed, VfaUNet) and (committed.roughness is not None) == committed.config.roughness_features
    with pytest.raises(FecConfigError, match="unet"):
        NetConfig(architecture="thesis", roughness_features=True)


# -- selector interface --------------------------------------------------------------------------------
def test_bad_inputs_raise_precise_errors(cnn_selector: CnnFootholdSelector, hip_height: float) -> None:
    grid = course_map()
    kwargs = {"hip_height_m": hip_height, "twist": TWIST, "gait": TROT_SWING}
    wrong = FecInput(Leg.LF, np.zeros((31, 31)), hip_height, TWIST, TROT_SWING)
    with pytest.raises(
        PerceptionInputError, match=r"VFA CNN: heights must have the model's patch shape \(33, 33\), got \(31, 31\)"
    ):
        cnn_selector.predict([wrong])
    with pytest.raises(PerceptionInputError, match=r"FecInput.twist has non-finite value\(s\) at index \[1\]"):
        cnn_selector.select(Leg.LF, NOMINAL, grid, **{**kwargs, "twist": [0.1, np.nan, 0, 0, 0, 0]})
    with pytest.raises(PerceptionInputError, match=r"VFA: nominal_world must be 3 finite values"):
        cnn_selector.select(Leg.LF, [0.0, np.inf, 0.0], grid, **kwargs)
    with pytest.raises(PerceptionInputError, match=r"FecInput.hip_height_m must be a finite number"):
        cnn_selector.select(Leg.LF, NOMINAL, grid, **{**kwargs, "hip_height_m": float("nan")})
    with pytest.raises(PerceptionInputError, match=r"VFA: the heightmap is stamped 0.2000 s in the future"):
        cnn_selector.select(Leg.LF, NOMINAL, grid, map_age_s=-0.2, **kwargs)
    with pytest.raises(FecConfigError, match=r"max_map_age_s must be a finite value > 0"):
        CnnFootholdSelector(cnn_selector.evaluator, cnn_selector.net, max_map_age_s=-1.0)


def test_missing_or_stale_map_passes_the_nominal_through(cnn_selector: CnnFootholdSelector, hip_height: float) -> None:
    kwargs = {"hip_height_m": hip_height, "twist": TWIST, "gait": TROT_SWING}
    missing = cnn_selector.select(Leg.RH, NOMINAL, None, **kwargs)
    stale = cnn_selector.select(Leg.RH, NOMINAL, course_map(), map_age_s=1.0, **kwargs)
    assert (missing.status, stale.status) == (VfaStatus.NO_MAP, VfaStatus.STALE_MAP)
    for result in (missing, stale):
        assert not result.any_safe and result.offset_cells is None
        np.testing.assert_array_equal(result.selected, NOMINAL)


def test_flat_ground_keeps_the_nominal_and_batch_equals_single_calls(
    cnn_selector: CnnFootholdSelector, hip_height: float
) -> None:
    gap = GapPatch(name="gap", region=Region(NOMINAL[0] - 0.05, NOMINAL[0] + 0.05, -2, 2), depth_m=0.3,
                   start_height_m=0.0, **RIGID)  # fmt: skip
    for grid in (course_map(), course_map(gap)):
        requests = [FootholdRequest(leg, NOMINAL, hip_height, TWIST, TROT_SWING) for leg in LEGS]
        batch = cnn_selector.select_legs(requests, grid)
        for request, result in zip(requests, batch):
            single = cnn_selector.select(request.leg, NOMINAL, grid, hip_height_m=hip_height, twist=TWIST,
                                         gait=TROT_SWING)  # fmt: skip
            assert result.offset_cells == single.offset_cells and result.status is VfaStatus.SELECTED
            np.testing.assert_allclose(result.selected, single.selected)
    flat = cnn_selector.select_legs(requests[:1], course_map())[0]
    assert not flat.adapted


def test_unknown_cells_are_never_returned(evaluator: FootholdEvaluator, hip_height: float) -> None:
    net = VfaNet(NetConfig())
    with torch.no_grad():  # a network that always picks the centre cell
        for p in net.parameters():
            p.zero_()
        net.head[2].bias[16 * 33 + 16] = 1.0
    heights = np.array(course_map().heights)
    heights[35:46, 35:46] = np.nan  # around the nominal (map centre 40, 40)
    grid = HeightMapGrid(center_xy=tuple(NOMINAL[:2]), yaw=0.0, resolution_m=0.02, heights=heights)
    unverified = CnnFootholdSelector(evaluator, net, verify=False)
    result = unverified.select(Leg.LF, NOMINAL, grid, hip_height_m=hip_height, twist=TWIST, gait=TROT_SWING)
    assert result.status is VfaStatus.NO_SAFE_CANDIDATE and not result.any_safe


def test_verification_replaces_an_unsafe_choice_by_the_exact_search(
    evaluator: FootholdEvaluator, hip_height: float
) -> None:
    gap = GapPatch(name="gap", region=Region(NOMINAL[0] - 0.05, NOMINAL[0] + 0.05, -2, 2), depth_m=0.3,
                   start_height_m=0.0, **RIGID)  # fmt: skip
    grid = course_map(gap)
    net = VfaNet(NetConfig())
    with torch.no_grad():  # always the centre cell: in the gap here
        for p in net.parameters():
            p.zero_()
        net.head[2].bias[16 * 33 + 16] = 1.0
    kwargs = {"hip_height_m": hip_height, "twist": TWIST, "gait": TROT_SWING}
    verified = CnnFootholdSelector(evaluator, net, verify=True)
    exact = FootholdSelector(evaluator).select(Leg.LF, NOMINAL, grid, **kwargs)
    result = verified.select(Leg.LF, NOMINAL, grid, **kwargs)
    assert exact.adapted and result.offset_cells == exact.offset_cells
    np.testing.assert_allclose(result.selected, exact.selected)
    assert (verified.counters.verified, verified.counters.rejected) == (1, 1)
    flat = verified.select(Leg.LF, NOMINAL, course_map(), **kwargs)  # the centre is safe on flat ground
    assert not flat.adapted and verified.counters.rejected == 1


def test_single_candidate_check_equals_the_eroded_full_evaluation(
    cnn_selector: CnnFootholdSelector, evaluator: FootholdEvaluator, fresh_set: VfaDataset
) -> None:
    rng = np.random.default_rng(1)
    for i in range(0, len(fresh_set), 40):
        inp = fresh_set.fec_input(i)
        for index in rng.integers(0, 33 * 33, size=5):
            assert cnn_selector.is_safe(inp, int(index)) == bool(fresh_set.safe[i].reshape(-1)[index])


def test_fine_tuning_starts_from_the_weights_and_keeps_each_seeds_validation_split(
    evaluator: FootholdEvaluator, tmp_path
) -> None:
    from tal_lab.vital import train_vfa

    torch.manual_seed(0)
    init = tmp_path / "init.pt"
    hyq = EncodingConfig(nominal_hip_height_m=0.5867)  # what train_vfa derives from the HyQ model
    save_model(build_net(NetConfig(architecture="unet", decoder_channels=(8, 8, 8), encoding=hyq)), init)
    common = ["--data", str(tmp_path / "data"), "--samples-per-leg", "10", "--epochs", "1", "--batch-size", "16"]
    other = tmp_path / "other.pt"  # weights of another encoding would read the inputs wrongly: refused
    save_model(build_net(NetConfig(architecture="unet", encoding=EncodingConfig(nominal_hip_height_m=0.6))), other)
    with pytest.raises(SystemExit, match="encoding"):
        train_vfa.train(train_vfa.parse_args(["--out", str(tmp_path / "x"), "--init-weights", str(other), *common]))
    report = train_vfa.train(train_vfa.parse_args(
        ["--out", str(tmp_path / "out"), "--init-weights", str(init), "--extra-seeds", "5", *common]))  # fmt: skip
    assert report["net"]["decoder_channels"] == [8, 8, 8]  # the architecture of the file, not the defaults
    assert [h["epoch"] for h in report["history"]] == [0, 1] and report["optimiser"]["epochs_run"] == 1
    assert report["extra_seeds"] == [5] and report["init_weights"] == str(init)
    parts = [
        train_vfa.split(VfaDataset.load(tmp_path / "data" / f"train_seed{seed}_n10.npz"), 0.1, seed, True)
        for seed in (1, 5)
    ]  # fmt: skip
    assert report["validation_samples"] == sum(int((v.label >= 0).sum()) for _, v in parts)
    assert report["train_samples"] == sum(int((t.label >= 0).sum()) for t, _ in parts)
    # the seed-1 validation tuples are those of a run on seed 1 alone, whatever is added
    alone = train_vfa.training_sets(train_vfa.parse_args(["--out", "x", *common]), evaluator)[1]
    union = train_vfa.training_sets(train_vfa.parse_args(["--out", "x", "--extra-seeds", "5", *common]), evaluator)[1]
    np.testing.assert_array_equal(union.heights[: len(alone)], alone.heights)
    np.testing.assert_array_equal(union.label[: len(alone)], alone.label)
    assert len(union) == len(alone) + len(parts[1][1])
    saved = torch.load(tmp_path / "out" / "vfa_cnn.pt", weights_only=True)
    assert saved["metadata"]["best_epoch"] == report["best_epoch"]["epoch"]
    if report["best_epoch"]["epoch"] == 0:  # no epoch beat the start: the start is what is saved
        for key, value in torch.load(init, weights_only=True)["state_dict"].items():
            torch.testing.assert_close(saved["state_dict"][key], value)
    # --wide-seeds: one more set sampled with the wide hip range, after the standard ones
    wide = train_vfa.training_sets(train_vfa.parse_args(["--out", "x", "--wide-seeds", "6", "--wide-samples-per-leg",
                                                         "10", *common]), evaluator)[1]  # fmt: skip
    assert (tmp_path / "data" / "train_wide_seed6_n10.npz").exists()
    np.testing.assert_array_equal(wide.heights[: len(alone)], alone.heights)
    assert len(wide) > len(alone)
    for bad in (["--extra-seeds", "2"], ["--extra-seeds", "1"], ["--seed", "3"], ["--wide-seeds", "2"],
                ["--wide-seeds", "6", "6"]):
        with pytest.raises(SystemExit):
            train_vfa.parse_args(["--out", "x", *bad])



def test_select_on_combined_keeps_the_epoch_with_the_best_decoded_match_plus_safe(
    evaluator: FootholdEvaluator, tmp_path
) -> None:
    """--select-on combined: every epoch's validation record has the combined decode's rates, the kept epoch
    maximises their sum, and evaluate's decoded rates are those of vfa_decode.decode on the same outputs (with
    the argmax decode they equal the argmax's). Without the safe head the option is refused."""
    from tal_lab.vital import train_vfa

    torch.manual_seed(0)
    init = tmp_path / "init.pt"
    hyq = EncodingConfig(nominal_hip_height_m=0.5867)
    save_model(build_net(NetConfig(architecture="unet", decoder_channels=(8, 8, 8), encoding=hyq)), init)
    common = ["--data", str(tmp_path / "data"), "--samples-per-leg", "10", "--batch-size", "16"]
    args = train_vfa.parse_args(["--out", str(tmp_path / "out"), "--init-weights", str(init), "--epochs", "2",
                                 "--patience", "0", "--select-on", "combined", "--select-safe-weight", "2", *common])
    report = train_vfa.train(args)
    history = report["history"]
    assert [h["epoch"] for h in history] == [0, 1, 2]
    scores = [h["decoded_perfect_match"] + h["decoded_safe"] for h in history]
    assert report["best_epoch"]["epoch"] == history[int(np.argmax(scores))]["epoch"]
    assert report["optimiser"]["select_on"] == "combined" and report["optimiser"]["select_safe_weight"] == 2.0
    net = load_model(tmp_path / "out" / "vfa_cnn.pt")
    validation = train_vfa.training_sets(args, evaluator)[1]
    batches = train_vfa.Batches(validation, net.config.encoding)
    argmax = train_vfa.evaluate(net, batches, decode_settings=VfaDecode(mode="argmax"))
    assert (argmax["decoded_perfect_match"], argmax["decoded_safe"]) == (argmax["perfect_match"], argmax["safe"])
    combined = train_vfa.evaluate(net, batches, decode_settings=VfaDecode(mode="combined", safe_weight=2.0))
    image, scalars, label, safe_mask = batches.tensors(np.arange(len(batches)))
    with torch.inference_mode():
        logits, safe_logits = net(image, scalars)
    chosen = decode_choices(VfaDecode(mode="combined", safe_weight=2.0), logits.numpy(), torch.sigmoid(safe_logits).numpy(),
                    image[:, 1].reshape(len(batches), -1).numpy() > 0.5)
    assert combined["decoded_perfect_match"] == pytest.approx(float(np.mean(chosen == label.numpy())))
    assert combined["decoded_safe"] == pytest.approx(float(safe_mask.numpy()[np.arange(len(chosen)), chosen].mean()))
    with pytest.raises(SystemExit):
        train_vfa.parse_args(["--out", "x", "--select-on", "combined", "--safe-weight", "0"])

# -- the committed weights -----------------------------------------------------------------------------
def test_committed_weights_approximate_the_exact_vfa(cnn_selector: CnnFootholdSelector, fresh_set: VfaDataset) -> None:
    scored = np.flatnonzero(fresh_set.label >= 0)
    choices = cnn_selector.predict([fresh_set.fec_input(i) for i in scored])
    match = float(np.mean(choices == fresh_set.label[scored]))
    safe = float(np.mean(fresh_set.safe.reshape(len(fresh_set), -1)[scored, choices]))
    adapted = fresh_set.label[scored] != 16 * 33 + 16
    match_adapted = float(np.mean(choices[adapted] == fresh_set.label[scored][adapted]))
    assert scored.size > 300 and adapted.sum() > 150
    assert match >= MIN_PERFECT_MATCH, f"perfect match {match:.3f} on {scored.size} fresh samples"
    assert safe >= MIN_SAFE, f"safe {safe:.3f} on {scored.size} fresh samples"
    assert match_adapted >= MIN_PERFECT_MATCH_ADAPTED, f"perfect match {match_adapted:.3f} where g != nominal"


def test_committed_weights_are_the_unet_with_their_tuned_decode(cnn_selector: CnnFootholdSelector) -> None:
    assert cnn_selector.net.config.architecture == "unet"
    assert cnn_selector.decode == VfaDecode("combined", safe_weight=1.5, distance_weight=0.0)


def test_committed_weights_cover_the_hips_of_the_closed_loop(cnn_selector: CnnFootholdSelector,
                                                             evaluator: FootholdEvaluator) -> None:
    """On tuples whose hips are 0.40-0.80 m above the patch (the wide range; the closed loop's hips left the
    standard 0.52-0.66 m on the stairs) the committed weights match the exact g in 71.9 % of these 100 per
    leg (seed 8, never trained on); the weights before the wide fine-tuning matched 65.1 %."""
    wide = generate(evaluator, seed=8, count=100, progress=False, hip_range="wide")
    scored = np.flatnonzero(wide.label >= 0)
    choices = cnn_selector.predict([wide.fec_input(i) for i in scored])
    match = float(np.mean(choices == wide.label[scored]))
    assert scored.size > 250 and match >= 0.68, f"perfect match {match:.3f} on {scored.size} wide-hip samples"


# -- the fast inference path (vfa_cnn_fast) -------------------------------------------------------------
def _encoded(inputs: list[FecInput], cfg: EncodingConfig) -> tuple[torch.Tensor, torch.Tensor]:
    gait = np.array([[i.gait.step_frequency_hz, i.gait.duty_factor, i.gait.swing_time_left_s, i.gait.step_height_m]
                     for i in inputs])  # fmt: skip
    image, scalars = encode(cfg, np.stack([i.heights for i in inputs]), np.array([i.hip_height_m for i in inputs]),
                            np.stack([i.twist for i in inputs]), gait, np.array([int(i.leg) for i in inputs]))  # fmt: skip
    return torch.from_numpy(image), torch.from_numpy(scalars)


def test_fast_path_scores_equal_the_plain_forward_on_random_networks(fresh_set: VfaDataset) -> None:
    """FastVfaUNet = VfaUNet.forward (float32 rounding only) for untrained networks of other widths, any batch."""
    torch.manual_seed(4)
    for channels, decoder, blocks in (((8, 16, 32), (32, 16, 8), 0), ((4, 8, 12), (6, 5, 3), 0),
                                      ((8, 16, 32), (32, 16, 16), 2)):  # fmt: skip
        net = build_net(NetConfig(channels=channels, hidden=64, architecture="unet", decoder_channels=decoder,
                                  head_blocks=blocks)).eval()  # fmt: skip
        for block in net.head:  # non-trivial blocks (default init is small): each must change the result
            torch.nn.init.normal_(block.weight, std=0.3)
        fast = compile_fast_unet(net, 33)
        for start, size in ((0, 1), (1, 4), (5, 9)):
            image, scalars = _encoded([fresh_set.fec_input(i) for i in range(start, start + size)], net.config.encoding)
            with torch.inference_mode():
                plain, plain_safe = net(image, scalars)
                logits, safe_logits = fast(image, scalars)
            assert logits.shape == plain.shape == (size, 33 * 33)
            scale = float(plain.abs().max()) + float(plain_safe.abs().max())
            torch.testing.assert_close(logits, plain, rtol=0.0, atol=1e-5 * scale)
            torch.testing.assert_close(safe_logits, plain_safe, rtol=0.0, atol=1e-5 * scale)


def test_fast_path_selects_what_the_plain_forward_selects(evaluator: FootholdEvaluator, fresh_set: VfaDataset) -> None:
    """The committed weights: same scores (to float32 rounding) and the same choice on 400 fresh tuples;
    a choice may only differ where the plain scores are tied to within the rounding."""
    net = load_model(DEFAULT_WEIGHTS)
    fast = CnnFootholdSelector(evaluator, net, verify=False, backend="torch")
    plain = CnnFootholdSelector(evaluator, net, verify=False, fast=False, backend="torch")
    assert fast.fast and not plain.fast
    inputs = [fresh_set.fec_input(i) for i in range(len(fresh_set))]
    image, scalars = _encoded(inputs, net.config.encoding)
    with torch.inference_mode():
        expected, expected_safe = net(image, scalars)
        logits, safe_logits = fast._fast_net(image, scalars)
    scale = float(expected.abs().max())
    assert float((logits - expected).abs().max()) <= 1e-5 * scale
    assert float((torch.sigmoid(safe_logits) - torch.sigmoid(expected_safe)).abs().max()) <= 1e-5
    choices, reference = fast.predict(inputs), plain.predict(inputs)
    differ = np.flatnonzero(choices != reference)
    top2 = torch.topk(expected, 2, dim=1).values
    assert np.all((top2[differ, 0] - top2[differ, 1]).numpy() <= 1e-5 * scale), f"choices differ at {differ}"
    assert differ.size <= 2 and len(set(reference.tolist())) > 20  # the tuples do not all select the same cell


def test_fast_path_is_used_only_for_a_unet_with_a_safe_head(evaluator: FootholdEvaluator) -> None:
    thesis = build_net(NetConfig(architecture="thesis")).eval()
    no_safe = build_net(NetConfig(architecture="unet", safe_head=False)).eval()
    rough = build_net(NetConfig(architecture="unet", roughness_features=True)).eval()
    assert not CnnFootholdSelector(evaluator, thesis, verify=False, backend="torch").fast
    assert not CnnFootholdSelector(evaluator, no_safe, verify=False, backend="torch").fast
    assert not CnnFootholdSelector(evaluator, rough, verify=False, backend="torch").fast  # no rearranged form
    with pytest.raises(ValueError, match="safe-mask head"):
        compile_fast_unet(no_safe, 33)


# -- the ONNX Runtime backend (vfa_cnn_ort) ------------------------------------------------------------
def test_onnxruntime_logits_equal_the_torch_forward_on_random_inputs() -> None:
    """OrtVfaNet = the module's forward (float32 rounding only) on random inputs, for untrained networks of
    both architectures, two widths, with and without the safe head, batch sizes 1, 4 and 7."""
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    from tal_perception.vfa_cnn_ort import OrtVfaNet

    torch.manual_seed(5)
    rng = np.random.default_rng(5)
    configs = (
        NetConfig(architecture="unet"),
        NetConfig(channels=(16, 32, 64), hidden=64, architecture="unet", decoder_channels=(64, 32, 16)),
        NetConfig(architecture="unet", safe_head=False),
        NetConfig(architecture="thesis", hidden=64),
        NetConfig(architecture="unet", decoder_channels=(32, 16, 16), roughness_features=True),
        NetConfig(architecture="unet", decoder_channels=(32, 16, 16), head_blocks=2),
    )
    for config in configs:
        net = build_net(config).eval()
        ort_net = OrtVfaNet(net)
        for size in (1, 4, 7):
            image = rng.normal(size=(size, 4, 33, 33)).astype(np.float32)
            image[:, 1] = rng.random((size, 33, 33)) < 0.2  # the unknown mask is 0 / 1
            scalars = rng.normal(size=(size, config.encoding.scalar_count)).astype(np.float32)
            logits, safe_logits = ort_net(image, scalars)
            with torch.inference_mode():
                expected, expected_safe = net(torch.from_numpy(image), torch.from_numpy(scalars))
            assert logits.shape == (size, 33 * 33)
            scale = float(expected.abs().max())
            np.testing.assert_allclose(logits, expected.numpy(), rtol=0.0, atol=1e-5 * scale)
            if config.safe_head:
                np.testing.assert_allclose(safe_logits, expected_safe.numpy(), rtol=0.0, atol=1e-5 * scale)
            else:
                assert safe_logits is None and expected_safe is None


def test_onnxruntime_backend_selects_what_the_torch_backend_selects(
    evaluator: FootholdEvaluator, fresh_set: VfaDataset
) -> None:
    """The committed weights with their stored decode and with the argmax: the same choice on 400 fresh
    tuples; a choice may only differ where the torch scores are tied to within the rounding."""
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    net = load_model(DEFAULT_WEIGHTS)
    inputs = [fresh_set.fec_input(i) for i in range(len(fresh_set))]
    image, scalars = _encoded(inputs, net.config.encoding)
    with torch.inference_mode():
        expected, _ = net(image, scalars)
    scale = float(expected.abs().max())
    top2 = torch.topk(expected, 2, dim=1).values
    for decode in (None, VfaDecode("argmax")):
        ort_sel = CnnFootholdSelector(evaluator, net, verify=False, decode=decode, backend="onnxruntime")
        torch_sel = CnnFootholdSelector(evaluator, net, verify=False, decode=decode, backend="torch")
        assert (ort_sel.backend, torch_sel.backend) == ("onnxruntime", "torch")
        assert not ort_sel.fast and torch_sel.fast
        choices, reference = ort_sel.predict(inputs), torch_sel.predict(inputs)
        differ = np.flatnonzero(choices != reference)
        assert np.all((top2[differ, 0] - top2[differ, 1]).numpy() <= 1e-5 * scale), f"choices differ at {differ}"
        assert differ.size <= 2 and len(set(reference.tolist())) > 20


def test_backend_defaults_to_onnxruntime_and_falls_back_to_torch_without_it(
    evaluator: FootholdEvaluator, monkeypatch: pytest.MonkeyPatch
) -> None:
    from tal_perception import vfa_cnn_ort

    net = build_net(NetConfig(architecture="unet")).eval()
    with pytest.raises(FecConfigError, match="backend"):
        CnnFootholdSelector(evaluator, net, verify=False, backend="tensorrt")
    expected_default = "onnxruntime" if vfa_cnn_ort.available() else "torch"
    assert CnnFootholdSelector(evaluator, net, verify=False).backend == expected_default
    monkeypatch.setattr(vfa_cnn_ort, "available", lambda: False)
    auto = CnnFootholdSelector(evaluator, net, verify=False)
    assert auto.backend == "torch" and auto.fast
    with pytest.warns(RuntimeWarning, match="onnxruntime"):
        explicit = CnnFootholdSelector(evaluator, net, verify=False, backend="onnxruntime")
    assert explicit.backend == "torch"
    assert explicit.predict([]).shape == (0,)


# -- Net2Net widening (widen_vfa) -----------------------------------------------------------------------
def _small_unet_reference(
    fresh_set: VfaDataset, seed: int
) -> tuple[torch.nn.Module, tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]:
    """A random small VfaUNet and (image, scalars, logits, safe logits) of it on six encoded tuples: the
    reference that a function-preserving edit of the network must reproduce."""
    torch.manual_seed(seed)
    net = build_net(NetConfig(architecture="unet", hidden=64)).eval()
    image, scalars = _encoded([fresh_set.fec_input(i) for i in range(6)], net.config.encoding)
    with torch.inference_mode():
        expected, expected_safe = net(image, scalars)
    return net, (image, scalars, expected, expected_safe)


def _assert_same_function(candidate: torch.nn.Module, image: torch.Tensor, scalars: torch.Tensor, expected: torch.Tensor,
                          expected_safe: torch.Tensor) -> None:  # fmt: skip
    """``candidate`` gives the reference's logits and safe logits (to 1e-5 of their largest magnitude)."""
    scale = float(expected.abs().max())
    with torch.inference_mode():
        logits, safe_logits = candidate(image, scalars)
    torch.testing.assert_close(logits, expected, rtol=0.0, atol=1e-5 * scale)
    torch.testing.assert_close(safe_logits, expected_safe, rtol=0.0, atol=1e-5 * scale)


def test_widening_computes_the_same_function_and_noise_separates_the_copies(fresh_set: VfaDataset) -> None:
    from tal_lab.vital.widen_vfa import widen_unet

    net, reference = _small_unet_reference(fresh_set, seed=6)
    for channels, decoder in (((8, 16, 32), (32, 16, 16)), ((16, 32, 64), (64, 32, 16)), ((8, 32, 32), (32, 16, 24))):
        wide = widen_unet(net, channels, decoder)
        assert (wide.config.channels, wide.config.decoder_channels) == (channels, decoder)
        _assert_same_function(wide, *reference)
    noisy = widen_unet(net, (8, 16, 32), (32, 16, 16), noise=0.01)
    first, copy = noisy.decoders[2].weight.detach()[:8], noisy.decoders[2].weight.detach()[8:]
    assert not torch.equal(first, copy) and float((first - copy).abs().max()) < 0.1 * float(first.abs().max())
    with pytest.raises(ValueError, match="multiples"):
        widen_unet(net, (12, 16, 32), (32, 16, 8))


def test_onnxruntime_binding_equals_the_session_call() -> None:
    """OrtVfaNet.bind: runs on the buffers' current contents into the same output arrays, with the outputs of
    the plain call bit for bit (with and without the safe head)."""
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    from tal_perception.vfa_cnn_ort import OrtVfaNet

    torch.manual_seed(6)
    rng = np.random.default_rng(6)
    for config in (NetConfig(architecture="unet"), NetConfig(architecture="unet", safe_head=False)):
        ort_net = OrtVfaNet(build_net(config).eval())
        image = np.empty((2, 4, 33, 33), np.float32)
        scalars = np.empty((2, config.encoding.scalar_count), np.float32)
        binding = ort_net.bind(image, scalars)
        for _ in range(2):  # new contents, same buffers
            image[...] = rng.normal(size=image.shape)
            scalars[...] = rng.normal(size=scalars.shape)
            logits, safe_logits = binding.run()
            expected, expected_safe = ort_net(image.copy(), scalars.copy())
            assert logits is binding.logits
            np.testing.assert_array_equal(logits, expected)
            if config.safe_head:
                np.testing.assert_array_equal(safe_logits, expected_safe)
            else:
                assert safe_logits is None and expected_safe is None
        with pytest.raises(ValueError, match="C-contiguous float32"):
            ort_net.bind(image.astype(np.float64), scalars)


def test_graph_rewrites_keep_the_outputs_bit_for_bit() -> None:
    """vfa_cnn_ort.rewrite_graph (applied by export_onnx): fewer Slice / Unsqueeze nodes in the exported VfaUNet
    graph (its crops and bias broadcasts), LeakyRelu only after a Conv (the others are Max(x, alpha * x)), and
    the same outputs bit for bit, for both architectures, batch sizes 1 and 5, inputs with large negative and
    positive values."""
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    import onnx
    import onnxruntime as ort

    from tal_perception import vfa_cnn_ort

    torch.manual_seed(8)
    rng = np.random.default_rng(8)
    configs = (NetConfig(architecture="unet"), NetConfig(architecture="unet", roughness_features=True),
               NetConfig(architecture="thesis", hidden=64))  # fmt: skip
    for config in configs:
        net = build_net(config).eval()
        rewritten = vfa_cnn_ort.export_onnx(net)
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(vfa_cnn_ort, "rewrite_graph", lambda model: model)
            plain = vfa_cnn_ort.export_onnx(net)
        graph, plain_graph = onnx.load_from_string(rewritten).graph, onnx.load_from_string(plain).graph

        def count(g: onnx.GraphProto, op: str) -> int:
            return sum(node.op_type == op for node in g.node)

        producers = {output: node.op_type for node in graph.node for output in node.output}
        assert {producers[node.input[0]] for node in graph.node if node.op_type == "LeakyRelu"} == {"Conv"}
        assert count(graph, "Max") == count(plain_graph, "LeakyRelu") - count(graph, "LeakyRelu") > 0
        if config.architecture == "unet":  # one pair each per decoder level
            assert count(graph, "Slice") == count(plain_graph, "Slice") - 3
            assert count(graph, "Unsqueeze") == count(plain_graph, "Unsqueeze") - 3
        sessions = [ort.InferenceSession(m, vfa_cnn_ort.session_options()) for m in (plain, rewritten)]
        for size in (1, 5):
            feed = {"image": rng.normal(scale=10.0, size=(size, 4, 33, 33)).astype(np.float32),
                    "scalars": rng.normal(scale=10.0, size=(size, config.encoding.scalar_count)).astype(np.float32)}  # fmt: skip
            for expected, actual in zip(*(session.run(None, feed) for session in sessions)):
                np.testing.assert_array_equal(actual, expected)
                assert actual.tobytes() == expected.tobytes()  # also the sign of zeros


def _outcome(call: Callable[[], VfaResult]) -> tuple:
    """(result fields, or the error's type and message) of ``call()``: what select and select_legs must share."""
    try:
        r = call()
    except Exception as error:  # the comparison covers any error
        return type(error), str(error)
    return r.leg, r.nominal.tolist(), r.selected.tolist(), r.any_safe, r.status, r.safe_candidates, r.offset_cells


@pytest.mark.parametrize("verify", [False, True])
def test_select_is_select_legs_for_one_request(evaluator: FootholdEvaluator, hip_height: float, verify: bool) -> None:
    """``select`` (its own one-leg path) returns what ``select_legs`` returns for the same single request, and
    raises the same errors: selections on and off the map's heading, a gap, unknown cells around the nominal
    (NO_SAFE_CANDIDATE with a network that picks the centre), no map, a stale map, and each bad input."""
    selector = CnnFootholdSelector(evaluator, load_model(DEFAULT_WEIGHTS), verify=verify)
    centre_net = VfaNet(NetConfig())
    with torch.no_grad():  # always picks the centre cell
        for p in centre_net.parameters():
            p.zero_()
        centre_net.head[2].bias[16 * 33 + 16] = 1.0
    centre = CnnFootholdSelector(evaluator, centre_net, verify=verify)
    gap = GapPatch(name="gap", region=Region(NOMINAL[0] - 0.05, NOMINAL[0] + 0.05, -2, 2), depth_m=0.3,
                   start_height_m=0.0, **RIGID)  # fmt: skip
    holes = np.array(course_map().heights)
    holes[35:46, 35:46] = np.nan  # around the nominal (map centre 40, 40)
    unknown = HeightMapGrid(center_xy=tuple(NOMINAL[:2]), yaw=0.0, resolution_m=0.02, heights=holes)
    infinite = np.array(course_map().heights)
    infinite[40, 40] = np.inf
    kwargs = {"hip_height_m": hip_height, "twist": TWIST, "gait": TROT_SWING}
    cases = [  # (selector, leg, nominal, grid, keyword arguments)
        *((selector, leg, NOMINAL, grid, {**kwargs, "yaw": yaw}) for leg in LEGS for grid in (course_map(),
          course_map(gap)) for yaw in (None, 0.37)),  # fmt: skip
        (selector, Leg.LH, NOMINAL + [0.05, -0.03, 0.0], course_map(gap), {**kwargs, "twist": [0.5, 0.1, 0, 0, 0, 0]}),
        (centre, Leg.LF, NOMINAL, unknown, kwargs),
        (selector, Leg.RH, NOMINAL, None, kwargs),
        (selector, Leg.RH, NOMINAL, course_map(), {**kwargs, "map_age_s": 1.0}),
        (selector, Leg.RF, NOMINAL, course_map(), {**kwargs, "twist": [0.1, np.nan, 0, 0, 0, 0]}),
        (selector, Leg.RF, NOMINAL, course_map(), {**kwargs, "twist": [0.1, 0.0]}),
        (selector, Leg.RF, [0.0, np.inf, 0.0], course_map(), kwargs),
        (selector, Leg.RF, [0.0, 0.0], None, kwargs),
        (selector, Leg.RF, NOMINAL, course_map(), {**kwargs, "hip_height_m": float("nan")}),
        (selector, Leg.RF, NOMINAL, course_map(), {**kwargs, "gait": (1.5, 0.6, 0.2, 0.1)}),
        (selector, Leg.RF, NOMINAL, course_map(), {**kwargs, "map_age_s": -0.2}),
        (selector, Leg.RF, NOMINAL, None, {**kwargs, "map_age_s": float("nan")}),
        (selector, Leg.RF, NOMINAL, course_map(), {**kwargs, "yaw": float("inf")}),
        (selector, 7, NOMINAL, course_map(), kwargs),
        (selector, Leg.RF, NOMINAL, HeightMapGrid(center_xy=tuple(NOMINAL[:2]), yaw=0.0, resolution_m=0.02,
                                                  heights=infinite), kwargs),  # fmt: skip
    ]
    for sel, leg, nominal, grid, options in cases:
        options = dict(options)
        yaw, map_age_s = options.pop("yaw", None), options.pop("map_age_s", 0.0)
        request = FootholdRequest(leg, nominal, options["hip_height_m"], options["twist"], options["gait"])
        batch = _outcome(lambda: sel.select_legs([request], grid, yaw=yaw, map_age_s=map_age_s)[0])  # noqa: B023
        single = _outcome(lambda: sel.select(leg, nominal, grid, yaw=yaw, map_age_s=map_age_s, **options))  # noqa: B023
        assert single == batch, (leg, grid is None, options)
    # the cases above include each status (with the verification the exact search replaces the unknown cell)
    expected = VfaStatus.SELECTED if verify else VfaStatus.NO_SAFE_CANDIDATE
    assert centre.select(Leg.LF, NOMINAL, unknown, **kwargs).status is expected
    assert selector.select(Leg.RH, NOMINAL, None, **kwargs).status is VfaStatus.NO_MAP
    assert selector.select(Leg.RH, NOMINAL, course_map(), map_age_s=1.0, **kwargs).status is VfaStatus.STALE_MAP
    assert selector.select(Leg.LF, NOMINAL, course_map(gap), **kwargs).status is VfaStatus.SELECTED


@pytest.mark.parametrize("verify", [False, True])
def test_select_legs_equals_predict_on_the_extracted_patches(
    evaluator: FootholdEvaluator, hip_height: float, verify: bool
) -> None:
    """select_legs' own path (batched extraction into reused buffers, bound ONNX Runtime outputs, in-place
    decode) chooses what ``predict`` chooses on FecInputs built with ``extract_patch``, for 1 to 5 legs per
    call (5: no buffers), headings aligned with the map or not, patches partly off the map."""
    selector = CnnFootholdSelector(evaluator, load_model(DEFAULT_WEIGHTS), verify=verify)
    gap = GapPatch(name="gap", region=Region(0.35, 0.45, -2, 2), depth_m=0.3, start_height_m=0.0, **RIGID)
    grid = extract_heightmap(Course("test", Region(-3, 3, -3, 3), DefaultGround(height_m=0.0, **RIGID), (gap,)),
                             (0.0, 0.0), 0.1, 61, 61, 0.02)  # fmt: skip
    rng = np.random.default_rng(7)
    for yaw in (grid.yaw, grid.yaw + 0.37):
        for count in range(1, 6):
            nominals = [np.array([rng.uniform(0.2, 0.7), rng.uniform(-0.6, 0.6), 0.0]) for _ in range(count)]
            legs = [LEGS[k % len(LEGS)] for k in range(count)]
            requests = [FootholdRequest(leg, nominal, hip_height + rng.uniform(-0.03, 0.03), TWIST, TROT_SWING)
                        for leg, nominal in zip(legs, nominals)]  # fmt: skip
            results = selector.select_legs(requests, grid, yaw=yaw)
            inputs = [FecInput(r.leg, extract_patch(grid, r.nominal_world[:2], yaw, 33, 0.02), r.hip_height_m, TWIST,
                               TROT_SWING) for r in requests]  # fmt: skip
            for inp, result, index in zip(inputs, results, selector.predict(inputs)):
                if verify and not selector.is_safe(inp, int(index)):
                    continue  # replaced by the exact search
                if not np.isfinite(inp.heights.reshape(-1)[index]):
                    assert result.status is VfaStatus.NO_SAFE_CANDIDATE
                    continue
                assert result.offset_cells == (int(index) // 33 - 16, int(index) % 33 - 16)
                assert result.selected[2] == inp.heights.reshape(-1)[index]


def test_adding_the_roughness_features_keeps_the_function_until_trained(fresh_set: VfaDataset) -> None:
    from tal_lab.vital.widen_vfa import add_roughness_features, widen_unet

    net, reference = _small_unet_reference(fresh_set, seed=9)
    image, scalars, expected, _ = reference
    scale = float(expected.abs().max())
    rough = add_roughness_features(net)
    wide = widen_unet(rough, (8, 16, 32), (32, 16, 16))  # widening keeps the option and the function
    for candidate in (rough, wide):
        assert candidate.config.roughness_features
        _assert_same_function(candidate, *reference)
    with torch.no_grad():  # the new inputs are live: weights on them change the output
        rough.decoders[2].weight[:, 16 + 8 + 2] += 0.5
        assert not torch.allclose(rough(image, scalars)[0], expected, atol=1e-3 * scale)
    with pytest.raises(ValueError, match="without the roughness"):
        add_roughness_features(rough)


def test_head_blocks_start_as_the_same_function_save_load_and_widen(fresh_set: VfaDataset, tmp_path) -> None:
    """``deepen_head`` adds zero residual 1 x 1 blocks: the function is unchanged until their weights move
    (and then it changes); the block count is saved, files without the key load with 0; widening keeps the
    blocks unless it would widen the layer they read; the option needs the unet."""
    from tal_lab.vital.widen_vfa import deepen_head, widen_unet

    net, reference = _small_unet_reference(fresh_set, seed=10)
    image, scalars, expected, _ = reference
    deep = deepen_head(net, 2)
    assert deep.config.head_blocks == 2 and len(deep.head) == 2
    _assert_same_function(deep, *reference)
    wide = widen_unet(deep, (16, 32, 64), (64, 32, 8))
    assert wide.config.head_blocks == 2
    _assert_same_function(wide, *reference)
    with pytest.raises(ValueError, match="head blocks"):
        widen_unet(deep, (8, 16, 32), (32, 16, 16))
    with torch.no_grad():
        deep.head[1].weight.normal_(std=0.3)
        deep.head[1].bias.fill_(0.1)
        changed = deep(image, scalars)[0]
    assert not torch.allclose(changed, expected, atol=1e-3 * float(expected.abs().max()))
    save_model(deep, tmp_path / "deep.pt")
    loaded = load_model(tmp_path / "deep.pt")
    assert loaded.config == deep.config
    with torch.inference_mode():
        torch.testing.assert_close(loaded(image, scalars)[0], changed, rtol=0.0, atol=1e-2 * float(changed.abs().max()))
    save_model(net, tmp_path / "old.pt")
    document = torch.load(tmp_path / "old.pt", weights_only=True)
    del document["net"]["head_blocks"]  # as written before the option existed
    torch.save(document, tmp_path / "old.pt")
    assert load_model(tmp_path / "old.pt").config.head_blocks == 0
    with pytest.raises(FecConfigError, match="head_blocks"):
        NetConfig(architecture="thesis", head_blocks=1)
    with pytest.raises(FecConfigError, match="head_blocks"):
        NetConfig(architecture="unet", head_blocks=-1)
    with pytest.raises(ValueError, match="blocks >= 1"):
        deepen_head(net, 0)


# -- canonical legs: right legs through their left mirror ----------------------------------------------
def test_canonical_set_holds_each_tuple_once_in_a_left_legs_frame(evaluator: FootholdEvaluator) -> None:
    data = generate(evaluator, seed=9, count=2, progress=False)
    canonical = canonical_legs(data)
    assert len(canonical) == len(data)
    assert set(canonical.leg.tolist()) == {Leg.LF, Leg.LH}
    left = np.isin(data.leg, [Leg.LF, Leg.LH])
    np.testing.assert_array_equal(canonical.heights[: left.sum()], data.heights[left])
    mirror = mirrored(data.subset(~left))  # the right legs' tuples, mirrored: exact labels of the left side
    np.testing.assert_array_equal(canonical.heights[left.sum():], mirror.heights)
    np.testing.assert_array_equal(canonical.label[left.sum():], mirror.label)


def test_canonical_inputs_mirror_only_the_right_legs_and_indices_map_back() -> None:
    rng = np.random.default_rng(0)
    heights = rng.normal(size=(4, 33, 33))
    twist = rng.normal(size=(4, 6))
    legs = np.array([Leg.LF, Leg.RF, Leg.LH, Leg.RH])
    out_heights, out_twist, out_legs, flip = canonical_inputs(heights, twist, legs)
    assert flip.tolist() == [False, True, False, True]
    assert out_legs.tolist() == [Leg.LF, Leg.LF, Leg.LH, Leg.LH]
    np.testing.assert_array_equal(out_heights[0], heights[0])
    np.testing.assert_array_equal(out_heights[1], heights[1][:, ::-1])
    np.testing.assert_array_equal(out_twist[3], twist[3] * [1, -1, 1, 1, 1, -1])
    np.testing.assert_array_equal(out_twist[2], twist[2])
    assert heights[1, 0, 0] == out_heights[1, 0, 32]  # the caller's arrays are not modified
    index = np.array([0, 34, 32 * 33 + 5, 33 * 33 - 1])  # (0, 0), (1, 1), (32, 5), (32, 32)
    np.testing.assert_array_equal(mirror_cell_index(index, flip, 33), [0, 1 * 33 + 31, 32 * 33 + 5, 32 * 33])
    maps = np.arange(4 * 33 * 33, dtype=float).reshape(4, -1)
    mirrored_maps = mirror_cell_maps(maps.copy(), flip, 33)
    for i in range(4):  # the map's argmax moves as the index does
        assert mirror_cell_index(np.array([maps[i].argmax()]), flip[i:i + 1], 33)[0] == mirrored_maps[i].argmax()


def test_canonical_network_chooses_for_a_right_leg_the_mirror_of_its_left_choice(
    evaluator: FootholdEvaluator, fresh_set: VfaDataset, tmp_path
) -> None:
    """A canonical network's choice for a right-leg tuple is the mirror of its choice for the tuple's mirror
    (a left leg); the selector and ``tune_vfa_decode.network_outputs`` agree; the flag survives saving and
    files without it load as not canonical."""
    torch.manual_seed(0)
    net = build_net(NetConfig(architecture="unet", decoder_channels=(8, 8, 8), canonical_legs=True)).eval()
    path = tmp_path / "canonical.pt"
    save_model(net, path)
    net = load_model(path)
    assert net.config.canonical_legs
    selector = CnnFootholdSelector(evaluator, net, verify=False, backend="torch")
    right = fresh_set.subset(np.isin(fresh_set.leg, [Leg.RF, Leg.RH]))
    mirror = mirrored(right)
    choices = selector.predict([right.fec_input(i) for i in range(len(right))])
    mirror_choices = selector.predict([mirror.fec_input(i) for i in range(len(mirror))])
    np.testing.assert_array_equal(choices, mirror_cell_index(mirror_choices, np.ones(len(right), bool), 33))
    logits, probability, unknown = network_outputs(net, right)
    np.testing.assert_array_equal(decode_choices(net.decode, logits, probability, unknown), choices)
    document = torch.load(path, weights_only=True)
    del document["net"]["canonical_legs"]
    torch.save(document, path)
    assert not load_model(path).config.canonical_legs


def test_training_with_canonical_legs_uses_left_legs_only(evaluator: FootholdEvaluator, tmp_path) -> None:
    from tal_lab.vital import train_vfa

    common = ["--data", str(tmp_path / "data"), "--samples-per-leg", "10", "--epochs", "1", "--batch-size", "16",
              "--decoder-channels", "8", "8", "8"]  # fmt: skip
    args = train_vfa.parse_args(["--out", str(tmp_path / "out"), "--canonical-legs", *common])
    train_set, val_set, _ = train_vfa.training_sets(args, evaluator)
    assert set(train_set.leg.tolist()) | set(val_set.leg.tolist()) == {Leg.LF, Leg.LH}
    assert len(train_set) + len(val_set) == 40  # each tuple once (the mirrored sets hold each twice)
    report = train_vfa.train(args)
    assert report["canonical_legs"] and report["net"]["canonical_legs"] and not report["mirrored"]
    assert load_model(tmp_path / "out" / "vfa_cnn.pt").config.canonical_legs
    with pytest.raises(SystemExit):
        train_vfa.parse_args(["--out", "x", "--canonical-legs", "--no-mirror"])
