"""Decoding the VFA CNN's outputs into one candidate (flat, row-major index into the n x n patch).

The CNN (``vfa_cnn``) gives, per candidate, an optimum logit (the thesis' softmax output) and a
safe-mask probability (sigmoid of the second head). The exact g is "the safe candidate closest to the
nominal (the patch centre), ties in row-major order". Decodes (``VfaDecode.mode``):

* ``argmax``: the thesis' rule, argmax of the optimum logits;
* ``masked_argmax``: argmax of the optimum logits over the candidates with safe probability >= ``tau``;
* ``closest_safe``: the exact rule applied to the predicted safe mask (probability >= ``tau``): the passing
  candidate closest to the centre, ties in row-major order; with ``tie_band_cells2`` = b >= 0 the
  candidate with the highest optimum logit among the passing ones within d^2 <= d_min^2 + b [cells^2];
* ``combined``: no threshold; the argmax over the known candidates of the score
  optimum_logit + lambda * log(p_safe) - mu * d^2, lambda = ``safe_weight`` [-], mu =
  ``distance_weight`` [1/cells^2], d the distance from the nominal [cells]. The softmax of the optimum
  logits is the network's probability that a cell is g, so with mu = 0 the score is the log of
  P(g) * p_safe^lambda (a product of the two heads' beliefs, lambda weighting the safe head); mu > 0 adds
  the exact rule's preference for cells near the nominal. log(p_safe) is taken of p_safe clipped to
  >= 1e-30 (float32 sigmoids underflow to 0 below a logit of about -88).

Unknown (NaN) cells never pass (the exact FEC never selects them). When no candidate passes, the
masked decodes fall back to ``argmax`` over the known cells (and over all cells if none is known);
``combined`` takes the argmax of its score over the known cells (over all cells if none is known).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from tal_perception.errors import FecConfigError, PerceptionInputError

DECODE_MODES = ("argmax", "masked_argmax", "closest_safe", "combined")
_MIN_PROBABILITY = 1e-30  # clip of p_safe before the log (combined)


@dataclass(frozen=True)
class VfaDecode:
    """How the CNN's outputs become a candidate (see the module docstring).

    mode: one of ``DECODE_MODES``; tau [-]: safe-probability threshold in (0, 1) (masked modes only);
    tie_band_cells2 [cells^2]: ``closest_safe`` only; None = exact tie rule (row-major), >= 0 = the highest
    optimum logit among the passing candidates within that band of squared distance of the closest one.
    safe_weight [-] (lambda) and distance_weight [1/cells^2] (mu): ``combined`` only, both >= 0; the score
    is optimum_logit + lambda * log(p_safe) - mu * d^2 (tau is not used).
    """

    mode: str = "argmax"
    tau: float = 0.5
    tie_band_cells2: float | None = None
    safe_weight: float = 1.0
    distance_weight: float = 0.0

    def __post_init__(self) -> None:
        if self.mode not in DECODE_MODES:
            raise FecConfigError(f"VfaDecode.mode must be one of {DECODE_MODES}, got {self.mode!r}")
        tau = self.tau
        if isinstance(tau, bool) or not isinstance(tau, (int, float)) or not 0.0 < float(tau) < 1.0:
            raise FecConfigError(f"VfaDecode.tau must be a probability strictly between 0 and 1, got {tau!r}")
        band = self.tie_band_cells2
        if band is not None and (
            isinstance(band, bool) or not isinstance(band, (int, float)) or not 0.0 <= float(band) < float("inf")
        ):
            raise FecConfigError(
                f"VfaDecode.tie_band_cells2 must be None or a finite value >= 0 [cells^2], got {band!r}"
            )
        for name in ("safe_weight", "distance_weight"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= float(value) < float("inf"):
                raise FecConfigError(f"VfaDecode.{name} must be a finite value >= 0, got {value!r}")

    @property
    def needs_safe_head(self) -> bool:
        return self.mode != "argmax"

    def to_dict(self) -> dict[str, object]:
        """The settings as a JSON-able mapping; ``safe_weight`` and ``distance_weight`` only for ``combined``
        (so the files of the other modes read as before)."""
        values: dict[str, object] = {"mode": self.mode, "tau": float(self.tau), "tie_band_cells2": self.tie_band_cells2}
        if self.mode == "combined":
            values |= {"safe_weight": float(self.safe_weight), "distance_weight": float(self.distance_weight)}
        return values

    @classmethod
    def from_dict(cls, values: dict[str, object]) -> VfaDecode:
        """The decode stored by ``to_dict`` (unknown keys are an error, missing ones take the defaults)."""
        unknown = set(values) - {"mode", "tau", "tie_band_cells2", "safe_weight", "distance_weight"}
        if unknown:
            raise FecConfigError(f"VfaDecode: unknown settings {sorted(unknown)}")
        return cls(**values)  # type: ignore[arg-type]


@lru_cache(maxsize=4)
def _distance_sq(cells: int) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Squared distance from the centre of every flat candidate [cells^2] and the exact search order
    (by distance, ties row-major: ``vfa_dataset.search_order``)."""
    centre = cells // 2
    r, c = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
    d2 = ((r - centre) ** 2 + (c - centre) ** 2).reshape(-1).astype(np.float64)
    return d2, np.argsort(d2, kind="stable")


def decode(
    settings: VfaDecode,
    optimum_logits: NDArray[np.floating],
    safe_probability: NDArray[np.floating] | None,
    unknown: NDArray[np.bool_],
) -> NDArray[np.intp]:
    """Flat candidate index per sample.

    optimum_logits (B, n*n); safe_probability (B, n*n) in [0, 1] (not read by ``argmax``); unknown
    (B, n*n) True on unknown (NaN) cells; row-major candidate order, n odd (the nominal is the centre).
    """
    logits = np.asarray(optimum_logits)  # float32 or float64 as given: the same argmax either way
    if not np.issubdtype(logits.dtype, np.floating):
        logits = logits.astype(np.float64)
    unknown = np.asarray(unknown, dtype=bool)
    if logits.ndim != 2 or unknown.shape != logits.shape:
        raise PerceptionInputError(
            f"VFA decode: optimum_logits and unknown must both be (B, n*n), got {logits.shape} and {unknown.shape}"
        )
    cells = int(round(np.sqrt(logits.shape[1])))
    if cells * cells != logits.shape[1] or cells % 2 == 0:
        raise PerceptionInputError(f"VFA decode: {logits.shape[1]} candidates is not an odd square patch")
    if settings.mode == "argmax":
        return np.argmax(logits, axis=1).astype(np.intp)
    if safe_probability is None:
        raise PerceptionInputError(f"VFA decode {settings.mode!r} needs the safe-mask probabilities (a safe head)")
    probability = np.asarray(safe_probability)
    if probability.shape != logits.shape:
        raise PerceptionInputError(f"VFA decode: safe_probability must be {logits.shape}, got {probability.shape}")
    return decode_unchecked(settings, logits, probability, unknown, cells)


def decode_unchecked(
    settings: VfaDecode, logits: NDArray[np.floating], probability: NDArray[np.floating] | None,
    unknown: NDArray[np.bool_], cells: int,
) -> NDArray[np.intp]:  # fmt: skip
    """``decode`` without its checks and conversions, for arrays known to be right: float logits and
    probabilities (B, cells * cells) (probabilities may be None for ``argmax``), a bool ``unknown`` of that
    shape, ``cells`` odd. Why: the selector's calls of 1-4 legs decode its own network outputs, whose
    checks cost ~6 us of a ~0.5 ms call."""
    if settings.mode == "argmax":
        return np.argmax(logits, axis=1).astype(np.intp)
    if settings.mode == "combined":
        return _combined_choice(settings, logits, probability, unknown, cells)
    known = ~unknown
    passing = known & (probability >= np.float64(settings.tau))  # compared in float64 whatever the dtype
    if settings.mode == "masked_argmax":
        choice = _masked_argmax(logits, passing)
    else:
        choice = _closest(logits, passing, cells, settings.tie_band_cells2)
    none = ~passing.any(axis=1)
    if none.any():  # the fallback: argmax over the known cells (over all if none is known)
        choice[none] = _masked_argmax(logits[none], known[none])
    return choice.astype(np.intp, copy=False)


def combined_score(
    settings: VfaDecode, logits: NDArray[np.floating], probability: NDArray[np.floating], cells: int
) -> NDArray[np.float64]:
    """The ``combined`` score per candidate (B, n*n), float64: optimum_logit + lambda * log(max(p_safe, 1e-30))
    - mu * d^2, d [cells] from the centre (unknown cells are not excluded here)."""
    if settings.safe_weight:  # lambda * log(max(p, 1e-30)) + logit in place (one temporary)
        # float64 copies first: operations on one dtype skip the ufuncs' buffered casting (~2 us of ~15)
        score = probability.astype(np.float64)
        np.maximum(score, _MIN_PROBABILITY, out=score)
        np.log(score, out=score)
        score *= settings.safe_weight
        score += logits.astype(np.float64, copy=False)  # widening is exact; a + b == b + a in IEEE arithmetic
    else:
        score = logits.astype(np.float64)
    if settings.distance_weight:
        score -= settings.distance_weight * _distance_sq(cells)[0][None, :]
    return score


def _combined_choice(
    settings: VfaDecode, logits: NDArray[np.floating], probability: NDArray[np.floating], unknown: NDArray[np.bool_],
    cells: int,
) -> NDArray[np.intp]:  # fmt: skip
    """``_masked_argmax(combined_score(...), ~unknown)`` with the unknown cells' scores set to -inf in place
    (the same argmax; no masked copy of the scores, ~5 us less for a call of 1-4 legs)."""
    score = combined_score(settings, logits, probability, cells)
    np.copyto(score, -np.inf, where=unknown)
    choice = np.argmax(score, axis=1).astype(np.intp, copy=False)
    if any(score[row, column] == -np.inf for row, column in enumerate(choice.tolist())):
        # a row whose best is -inf (no known cell, or only -inf scores): redo it as _masked_argmax does
        return _masked_argmax(combined_score(settings, logits, probability, cells), ~unknown)
    return choice


def _masked_argmax(logits: NDArray[np.floating], allowed: NDArray[np.bool_]) -> NDArray[np.intp]:
    """argmax of the logits over the allowed candidates (over all where none is allowed)."""
    choice = np.argmax(np.where(allowed, logits, -np.inf), axis=1).astype(np.intp, copy=False)
    none = ~allowed.any(axis=1)
    if none.any():
        choice[none] = np.argmax(logits[none], axis=1)
    return choice


def _closest(
    logits: NDArray[np.floating], passing: NDArray[np.bool_], cells: int, band: float | None
) -> NDArray[np.intp]:
    """The passing candidate closest to the centre (exact tie rule, or the best logit within ``band``)."""
    d2, order = _distance_sq(cells)
    ranked = passing[:, order]
    first = order[np.argmax(ranked, axis=1)]  # row-major among equal distances, as the exact selector
    if band is None:
        return first
    near = passing & (d2[None, :] <= d2[first][:, None] + band)
    return _masked_argmax(logits, near)


__all__ = ["DECODE_MODES", "VfaDecode", "combined_score", "decode", "decode_unchecked"]
