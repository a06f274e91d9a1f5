"""VFA CNN decodes (``vfa_decode``) on hand-made outputs, and the decode / architecture stored with the weights."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tal_lab.vital.vfa_dataset import closest_safe_index

from tal_perception.errors import FecConfigError, PerceptionInputError
from tal_perception.fec import FootholdEvaluator
from tal_perception.vfa_cnn import (
    CnnFootholdSelector,
    EncodingConfig,
    NetConfig,
    VfaNet,
    VfaUNet,
    build_net,
    load_model,
    save_model,
    store_decode,
)
from tal_perception.vfa_decode import VfaDecode, combined_score, decode

N = 5  # a 5 x 5 patch: centre (2, 2) = flat index 12


def flat(row: int, col: int) -> int:
    return row * N + col


def outputs(safe_cells: dict[tuple[int, int], float], best: tuple[int, int]) -> tuple[np.ndarray, ...]:
    """One sample: safe probabilities 0.05 except ``safe_cells``; optimum logits peaking at ``best``."""
    probability = np.full((1, N * N), 0.05)
    for (r, c), p in safe_cells.items():
        probability[0, flat(r, c)] = p
    logits = np.zeros((1, N * N))
    logits[0, flat(*best)] = 5.0
    return logits, probability, np.zeros((1, N * N), bool)


def test_closest_safe_picks_the_predicted_safe_cell_closest_to_the_nominal() -> None:
    # (0, 0) has the best logit but is far; (2, 4) and (3, 3) pass tau; (2, 3) is close but below tau.
    logits, probability, unknown = outputs({(2, 4): 0.9, (3, 3): 0.8, (0, 0): 0.95, (2, 3): 0.4}, best=(0, 0))
    choice = decode(VfaDecode("closest_safe", tau=0.5), logits, probability, unknown)
    assert choice.tolist() == [flat(3, 3)]  # d^2 = 2 < 4
    assert choice[0] == closest_safe_index((probability[0] >= 0.5).reshape(N, N))  # the exact rule on the mask
    assert decode(VfaDecode("closest_safe", tau=0.3), logits, probability, unknown).tolist() == [flat(2, 3)]
    assert decode(VfaDecode("masked_argmax", tau=0.5), logits, probability, unknown).tolist() == [flat(0, 0)]
    assert decode(VfaDecode("argmax"), logits, probability, unknown).tolist() == [flat(0, 0)]


def test_closest_safe_ties_are_row_major_or_broken_by_the_logits_within_the_band() -> None:
    logits, probability, unknown = outputs({(1, 2): 0.9, (3, 2): 0.9, (2, 0): 0.9}, best=(3, 2))
    assert decode(VfaDecode("closest_safe"), logits, probability, unknown).tolist() == [flat(1, 2)]  # row-major
    assert decode(VfaDecode("closest_safe", tie_band_cells2=0.0), logits, probability, unknown).tolist() == [flat(3, 2)]
    logits[0, flat(2, 0)] = 9.0  # d^2 = 4: outside a band of 2, inside a band of 3
    assert decode(VfaDecode("closest_safe", tie_band_cells2=2.0), logits, probability, unknown).tolist() == [flat(3, 2)]
    assert decode(VfaDecode("closest_safe", tie_band_cells2=3.0), logits, probability, unknown).tolist() == [flat(2, 0)]


def test_masked_decodes_fall_back_to_the_argmax_when_no_cell_passes_tau() -> None:
    logits, probability, unknown = outputs({(0, 4): 0.6}, best=(4, 4))
    for mode in ("masked_argmax", "closest_safe"):
        assert decode(VfaDecode(mode, tau=0.7), logits, probability, unknown).tolist() == [flat(4, 4)]
        assert decode(VfaDecode(mode, tau=0.5), logits, probability, unknown).tolist() == [flat(0, 4)]


def test_unknown_cells_never_pass_and_the_fallback_avoids_them() -> None:
    logits, probability, unknown = outputs({(2, 2): 0.99, (0, 2): 0.8}, best=(2, 2))
    unknown[0, flat(2, 2)] = True
    assert decode(VfaDecode("closest_safe"), logits, probability, unknown).tolist() == [flat(0, 2)]
    probability[0, flat(0, 2)] = 0.1  # nothing passes: the fallback is the best known cell, not the unknown one
    logits[0, flat(4, 0)] = 1.0
    assert decode(VfaDecode("closest_safe"), logits, probability, unknown).tolist() == [flat(4, 0)]


def test_a_batch_is_decoded_sample_by_sample() -> None:
    a = outputs({(1, 1): 0.9}, best=(0, 0))
    b = outputs({}, best=(4, 0))
    batch = [np.concatenate([x, y]) for x, y in zip(a, b)]
    assert decode(VfaDecode("closest_safe"), *batch).tolist() == [flat(1, 1), flat(4, 0)]


def test_combined_picks_a_safe_cell_over_a_likelier_unsafe_one() -> None:
    # (2, 3) has the best optimum logit but is predicted unsafe; (3, 3) is nearly as likely and predicted safe.
    logits, probability, unknown = outputs({(3, 3): 0.9}, best=(2, 3))
    logits[0, flat(2, 3)], logits[0, flat(3, 3)] = 3.0, 2.5
    assert decode(VfaDecode("argmax"), logits, probability, unknown).tolist() == [flat(2, 3)]
    # lambda 1: 3 + log 0.05 = 0.00 < 2.5 + log 0.9 = 2.39; lambda 0.1: 2.70 > 2.49 (the logits win)
    assert decode(VfaDecode("combined", safe_weight=1.0), logits, probability, unknown).tolist() == [flat(3, 3)]
    assert decode(VfaDecode("combined", safe_weight=0.1), logits, probability, unknown).tolist() == [flat(2, 3)]
    assert decode(VfaDecode("combined", safe_weight=0.0), logits, probability, unknown).tolist() == [flat(2, 3)]
    # no threshold: a cell below any usual tau is still chosen when it is the best trade
    probability[0, flat(3, 3)] = 0.2
    assert decode(VfaDecode("combined", safe_weight=1.0), logits, probability, unknown).tolist() == [flat(3, 3)]
    assert decode(VfaDecode("masked_argmax", tau=0.3), logits, probability, unknown).tolist() == [flat(2, 3)]


def test_combined_distance_penalty_prefers_the_cell_nearer_the_nominal() -> None:
    # two cells predicted equally safe: (0, 0) (d^2 = 8) with logit 5, (2, 3) (d^2 = 1) with logit 4.
    logits, probability, unknown = outputs({(0, 0): 0.9, (2, 3): 0.9}, best=(0, 0))
    logits[0, flat(2, 3)] = 4.0
    assert decode(VfaDecode("combined"), logits, probability, unknown).tolist() == [flat(0, 0)]
    # mu (8 - 1) > 1 flips the choice: mu 0.2 -> 5 - 1.6 = 3.4 < 4 - 0.2 = 3.8; mu 0.1 -> 4.2 > 3.9
    assert decode(VfaDecode("combined", distance_weight=0.2), logits, probability, unknown).tolist() == [flat(2, 3)]
    assert decode(VfaDecode("combined", distance_weight=0.1), logits, probability, unknown).tolist() == [flat(0, 0)]
    expected = logits[0] + np.log(probability[0]) - 0.2 * np.array(
        [(r - 2) ** 2 + (c - 2) ** 2 for r in range(N) for c in range(N)], float
    )  # fmt: skip
    np.testing.assert_allclose(combined_score(VfaDecode("combined", distance_weight=0.2), logits, probability, N)[0],
                               expected)  # fmt: skip


def test_combined_excludes_unknown_cells_and_survives_zero_probabilities() -> None:
    logits, probability, unknown = outputs({(2, 2): 0.99, (0, 2): 0.8}, best=(2, 2))
    unknown[0, flat(2, 2)] = True
    assert decode(VfaDecode("combined"), logits, probability, unknown).tolist() == [flat(0, 2)]
    probability[:] = 0.0  # float32 sigmoids underflow: log clipped, the logits still decide among the known cells
    logits[0, flat(4, 0)] = 1.0
    assert decode(VfaDecode("combined"), logits, probability.astype(np.float32), unknown).tolist() == [flat(4, 0)]
    unknown[:] = True  # nothing known: the argmax of the score over all cells
    assert decode(VfaDecode("combined"), logits, probability, unknown).tolist() == [flat(2, 2)]
    with pytest.raises(PerceptionInputError, match="needs the safe-mask probabilities"):
        decode(VfaDecode("combined"), logits, None, unknown)


@pytest.mark.parametrize("field", ["safe_weight", "distance_weight"])
@pytest.mark.parametrize("value", [-0.1, float("inf"), float("nan"), True, "1"])
def test_invalid_combined_weights_are_rejected(field: str, value: object) -> None:
    with pytest.raises(FecConfigError, match=f"{field} must be a finite value >= 0"):
        VfaDecode("combined", **{field: value})  # type: ignore[arg-type]


def test_combined_round_trips_and_the_other_modes_store_no_weights() -> None:
    settings = VfaDecode("combined", safe_weight=2.0, distance_weight=0.05)
    assert VfaDecode.from_dict(settings.to_dict()) == settings
    assert "safe_weight" not in VfaDecode("masked_argmax", 0.1).to_dict()
    assert VfaDecode("combined").needs_safe_head


@pytest.mark.parametrize("tau", [0.0, 1.0, -0.1, 1.5, float("nan"), True, "0.5"])
def test_invalid_tau_is_rejected_with_a_precise_error(tau: object) -> None:
    with pytest.raises(FecConfigError, match="tau must be a probability strictly between 0 and 1"):
        VfaDecode("closest_safe", tau=tau)  # type: ignore[arg-type]


def test_invalid_mode_band_and_shapes_are_rejected() -> None:
    with pytest.raises(FecConfigError, match="mode must be one of"):
        VfaDecode("nearest")
    with pytest.raises(FecConfigError, match="tie_band_cells2 must be None or a finite value >= 0"):
        VfaDecode("closest_safe", tie_band_cells2=-1.0)
    with pytest.raises(FecConfigError, match="unknown settings"):
        VfaDecode.from_dict({"mode": "argmax", "threshold": 0.5})
    logits, probability, unknown = outputs({}, best=(0, 0))
    with pytest.raises(PerceptionInputError, match="needs the safe-mask probabilities"):
        decode(VfaDecode("closest_safe"), logits, None, unknown)
    with pytest.raises(PerceptionInputError, match="safe_probability must be"):
        decode(VfaDecode("closest_safe"), logits, probability[:, :-1], unknown)
    with pytest.raises(PerceptionInputError, match="not an odd square patch"):
        decode(VfaDecode("argmax"), np.zeros((1, 16)), None, np.zeros((1, 16), bool))
    assert VfaDecode.from_dict(VfaDecode("closest_safe", 0.3, 2.0).to_dict()) == VfaDecode("closest_safe", 0.3, 2.0)


# -- the architectures and the stored decode -----------------------------------------------------------------
def test_unet_shapes_and_round_trip_with_its_decode(tmp_path) -> None:
    config = NetConfig(architecture="unet")
    net = build_net(config)
    assert isinstance(net, VfaUNet) and isinstance(build_net(NetConfig()), VfaNet)
    image, scalars = torch.randn(3, 4, 33, 33), torch.randn(3, EncodingConfig().scalar_count)
    optimum, safe = net(image, scalars)
    assert optimum.shape == (3, 33 * 33) and safe.shape == (3, 33 * 33)
    torch.testing.assert_close(net.optimum_logits(image, scalars), optimum)
    assert build_net(NetConfig(architecture="unet", safe_head=False))(image, scalars)[1] is None
    path = tmp_path / "unet.pt"
    save_model(net, path, {"decode": VfaDecode("closest_safe", 0.4, 1.0).to_dict()})
    loaded = load_model(path)
    assert loaded.config == config and loaded.decode == VfaDecode("closest_safe", 0.4, 1.0)
    torch.testing.assert_close(loaded(image, scalars)[1], safe, atol=0.05, rtol=0.05)  # float16 storage
    store_decode(path, VfaDecode("masked_argmax", 0.6))
    assert load_model(path).decode == VfaDecode("masked_argmax", 0.6)
    with pytest.raises(FecConfigError, match="architecture must be one of"):
        NetConfig(architecture="resnet")


def test_selector_uses_the_stored_decode_unless_given_one(evaluator: FootholdEvaluator, tmp_path) -> None:
    torch.manual_seed(0)
    path = tmp_path / "net.pt"
    save_model(VfaNet(NetConfig()), path)
    assert CnnFootholdSelector(evaluator, load_model(path)).decode == VfaDecode()  # no decode stored: argmax
    store_decode(path, VfaDecode("closest_safe", 0.5))
    net = load_model(path)
    assert CnnFootholdSelector(evaluator, net).decode == VfaDecode("closest_safe", 0.5)
    given = VfaDecode("masked_argmax", 0.2)
    assert CnnFootholdSelector(evaluator, net, decode=given).decode == given
    with pytest.raises(FecConfigError, match="decode must be a VfaDecode"):
        CnnFootholdSelector(evaluator, net, decode="closest_safe")  # type: ignore[arg-type]
    plain = tmp_path / "plain.pt"
    save_model(VfaNet(NetConfig(safe_head=False)), plain)
    with pytest.raises(FecConfigError, match="needs the safe-mask head"):
        CnnFootholdSelector(evaluator, load_model(plain), decode=VfaDecode("closest_safe"))
    with pytest.raises(FecConfigError, match="needs a safe head"):
        store_decode(plain, VfaDecode("closest_safe"))


def test_tune_vfa_decode_scores_the_grid_and_stores_the_best_decode(tmp_path) -> None:
    from tal_lab.vital import tune_vfa_decode

    torch.manual_seed(0)
    weights = tmp_path / "net.pt"
    save_model(build_net(NetConfig(architecture="unet")), weights)
    args = tune_vfa_decode.parse_args(
        ["--out", str(tmp_path / "out"), "--weights", str(weights), "--data", str(tmp_path / "data"),
         "--samples-per-leg", "3", "--test-samples-per-leg", "2", "--taus", "0.3", "0.7", "--bands", "-1", "2",
         "--safe-weights", "1", "4", "--distance-weights", "0", "0.1", "--store"]
    )  # fmt: skip
    summary = tune_vfa_decode.run(args)
    assert len(summary["grid"]) == 1 + 2 + 2 * 2 + 2 * 2 and set(summary["best"]) == set(tune_vfa_decode.MODES)
    assert summary["rule"] == "match_plus_safe"  # the default
    tuning_rows = [row["tuning"] for row in summary["best"].values()]
    best_sum = max(r["perfect_match"] + r["safe"] for r in tuning_rows)
    chosen_row = next(row["tuning"] for row in summary["best"].values() if row["decode"] == summary["chosen"])
    assert chosen_row["perfect_match"] + chosen_row["safe"] == best_sum  # chosen on the tuning set by the rule
    for row in summary["best"].values():
        m = row["test"]
        assert 0.0 <= m["perfect_match"] <= m["safe"] <= 1.0
        assert m["verified_equals_g"] == pytest.approx(m["perfect_match"] + 1.0 - m["safe"])
    assert load_model(weights).decode == VfaDecode.from_dict(summary["chosen"])
    report = (tmp_path / "out" / "vfa_cnn_decode.md").read_text()
    assert report.startswith("# VFA CNN decodes") and "perfect match + safe rate" in report
    with pytest.raises(SystemExit):
        tune_vfa_decode.parse_args(["--out", "x", "--seed", "2"])  # the tuning seed must not be the test seed


def test_selection_rules_trade_perfect_match_against_safe_rate() -> None:
    from tal_lab.vital.tune_vfa_decode import rule_key

    rows = [{"perfect_match": 0.74, "safe": 0.83}, {"perfect_match": 0.72, "safe": 0.88},
            {"perfect_match": 0.60, "safe": 0.95}]  # fmt: skip
    assert max(rows, key=lambda r: rule_key("match", r)) is rows[0]
    assert max(rows, key=lambda r: rule_key("match_plus_safe", r)) is rows[1]  # 1.60 > 1.57, 1.55
    tied = [{"perfect_match": 0.5, "safe": 0.75}, {"perfect_match": 0.75, "safe": 0.5}]  # equal sums (exact)
    assert max(tied, key=lambda r: rule_key("match_plus_safe", r)) is tied[1]  # then the higher perfect match
    with pytest.raises(ValueError, match="unknown selection rule"):
        rule_key("safe", rows[0])
