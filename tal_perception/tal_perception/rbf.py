"""Function approximation of the VPA: NSF(z_h) as a weighted sum of E fixed Gaussians (thesis appendix).

F(z, w) = sum_e w_e exp(-0.5 (z - c_e)^2 / sigma^2). The centres c_e are spaced equidistantly over the
sampled hip-height range and the common width sigma makes neighbouring Gaussians intersect at
``intersection`` (thesis example: 0.5; VPA default 0.7, see ``vpa_settings``). With fixed centres and
widths F is linear in w, so the weights are the least-squares solution of Phi w = nsf,
Phi[i, e] = g_e(z_i) (one pseudo-inverse, computed once; Phi's condition number is ~6 for 30
Gaussians at 0.7 over 31 samples, so no regularisation is needed).
Units: z [m] (relative hip height, see ``vpa_settings``), F in the unit of the fitted values.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tal_perception.errors import VpaConfigError

FloatArray = NDArray[np.float64]


class RbfBasis:
    """E Gaussians with fixed centres over [z_min, z_max] and the least-squares fit on the samples z_i."""

    def __init__(self, samples: ArrayLike, count: int, intersection: float = 0.7) -> None:
        z = np.asarray(samples, dtype=float).reshape(-1)
        if z.size < 2 or not np.all(np.diff(z) > 0.0):
            raise VpaConfigError(f"RBF samples must be >= 2 increasing hip heights [m], got {z!r}")
        if count < 2:
            raise VpaConfigError(f"RBF count must be >= 2, got {count}")
        self.samples = z
        self.centres = np.linspace(z[0], z[-1], count)
        spacing = float(self.centres[1] - self.centres[0])
        # exp(-0.5 (spacing / 2)^2 / sigma^2) = intersection at the midpoint between two centres
        self.sigma = 0.5 * spacing / math.sqrt(-2.0 * math.log(intersection))
        self.design = self.values(z)  # Phi (N, E)
        self.pseudo_inverse = np.linalg.pinv(self.design)  # (E, N)

    @property
    def count(self) -> int:
        return int(self.centres.size)

    def values(self, z: ArrayLike) -> FloatArray:
        """(..., E) Gaussians at hip heights z [m]."""
        d = (np.asarray(z, dtype=float)[..., None] - self.centres) / self.sigma
        return np.exp(-0.5 * d * d)

    def derivatives(self, z: ArrayLike) -> FloatArray:
        """(..., E) d g_e / dz [1/m] at hip heights z [m]."""
        d = (np.asarray(z, dtype=float)[..., None] - self.centres) / self.sigma
        return np.exp(-0.5 * d * d) * (-d / self.sigma)

    def fit(self, values: ArrayLike) -> FloatArray:
        """Least-squares weights (..., E) of the sampled values (..., N) (thesis: argmin S(w))."""
        v = np.asarray(values, dtype=float)
        if v.shape[-1] != self.samples.size:
            raise VpaConfigError(f"RBF fit needs {self.samples.size} values per curve, got shape {v.shape}")
        return v @ self.pseudo_inverse.T

    def evaluate(self, weights: ArrayLike, z: ArrayLike) -> FloatArray:
        """F(z, w): weights (..., E), z broadcastable to the leading shape of weights [m]."""
        return np.sum(np.asarray(weights, dtype=float) * self.values(z), axis=-1)

    def slope(self, weights: ArrayLike, z: ArrayLike) -> FloatArray:
        """dF/dz at z [unit/m]."""
        return np.sum(np.asarray(weights, dtype=float) * self.derivatives(z), axis=-1)
