"""VFA CNN decodes (``vfa_decode``) on hand-made outputs, and the decode / architecture stored with the weights."""

from __future__ import annotations

import numpy as np
import pytest
import torch

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
from tal_perception.vfa_dataset import closest_safe_index
from tal_perception.vfa_decode import VfaDecode, decode

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
    from tal_perception import tune_vfa_decode

    torch.manual_seed(0)
    weights = tmp_path / "net.pt"
    save_model(build_net(NetConfig(architecture="unet")), weights)
    args = tune_vfa_decode.parse_args(
        ["--out", str(tmp_path / "out"), "--weights", str(weights), "--data", str(tmp_path / "data"),
         "--samples-per-leg", "3", "--test-samples-per-leg", "2", "--taus", "0.3", "0.7", "--bands", "-1", "2",
         "--store"]
    )  # fmt: skip
    summary = tune_vfa_decode.run(args)
    assert len(summary["grid"]) == 1 + 2 + 2 * 2 and set(summary["best"]) == {"argmax", "masked_argmax", "closest_safe"}
    for row in summary["best"].values():
        m = row["test"]
        assert 0.0 <= m["perfect_match"] <= m["safe"] <= 1.0
        assert m["verified_equals_g"] == pytest.approx(m["perfect_match"] + 1.0 - m["safe"])
    assert load_model(weights).decode == VfaDecode.from_dict(summary["chosen"])
    assert (tmp_path / "out" / "vfa_cnn_decode.md").read_text().startswith("# VFA CNN decodes")
    with pytest.raises(SystemExit):
        tune_vfa_decode.parse_args(["--out", "x", "--seed", "2"])  # the tuning seed must not be the test seed
