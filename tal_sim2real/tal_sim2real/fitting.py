"""Fitting candidate effects by re-simulation, and the information criterion that chooses between them."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares, minimize_scalar

from .library import Candidate, Parameter

Residual = Callable[[dict[str, float]], np.ndarray]


@dataclass
class Fit:
    """A fitted model: the candidate names, parameter values [SI] with 95% intervals, cost (sum of squared
    residuals), number of observations for the criterion and the number of re-simulations it took."""

    candidates: tuple[str, ...]
    values: dict[str, float]
    intervals: dict[str, tuple[float, float]] = field(default_factory=dict)
    cost: float = math.inf
    n_obs: int = 1
    evaluations: int = 0
    validation_cost: float | None = None

    @property
    def n_params(self) -> int:
        return len(self.values)

    def bic(self) -> float:
        """Bayesian information criterion for Gaussian residuals of unknown variance."""
        return self.n_obs * math.log(max(self.cost, 1e-300) / self.n_obs) + self.n_params * math.log(self.n_obs)


def information_criterion(cost: float, n_eff: float, n_params: int) -> float:
    """BIC of Gaussian residuals with ``cost`` (sum of squares) on ``n_eff`` effective samples and
    ``n_params`` fitted parameters: n log(cost / n) + k log(n). Used to choose between a global effect and its
    per-leg or per-joint variant: each extra parameter costs log(n_eff)."""
    n = max(float(n_eff), 2.0)
    return n * math.log(max(cost, 1e-300) / n) + n_params * math.log(n)


def effective_samples(residual: np.ndarray) -> float:
    """Effective number of independent samples of a (samples, channels) residual: per channel
    N (1 - rho) / (1 + rho) with rho its lag-1 autocorrelation (>= 0), summed over channels. White noise
    counts every sample; a slowly varying model error counts few (so its fit is not over-rewarded)."""
    r = np.asarray(residual, dtype=float)
    if r.ndim == 1:
        r = r[:, None]
    total = 0.0
    for col in r.T:
        col = col - col.mean()
        denom = float(col @ col)
        rho = float(col[1:] @ col[:-1]) / denom if denom > 0 else 0.0
        rho = min(max(rho, 0.0), 0.999)
        total += len(col) * (1.0 - rho) / (1.0 + rho)
    return max(total, 2.0)


def fit_least_squares(
    candidates: list[Candidate],
    residual: Residual,
    start: dict[str, float],
    n_obs: int,
    max_evaluations: int = 16,
    rtol: float = 1e-8,
) -> Fit:
    """Bounded trust-region least squares (scipy) over the candidates' parameters, in internal (log for
    stiffness-like) coordinates, finite-difference Jacobian; intervals from the Jacobian at the optimum
    with the residual variance scaled to ``n_obs`` independent observations.

    ``max_evaluations`` bounds the trust-region iterations' own residual calls (scipy does not count the
    Jacobian's); ``rtol`` [-] stops when an iteration changes the cost or the internal parameters by less
    than that fraction (scipy's ftol and xtol)."""
    params: list[Parameter] = [p for c in candidates for p in c.parameters]
    lower = np.array([p.to_internal(p.lower) if not (p.log and p.lower <= 0) else -np.inf for p in params])
    upper = np.array([p.to_internal(p.upper) for p in params])
    x0 = np.array([p.to_internal(float(np.clip(start.get(p.name, p.probe), p.lower, p.upper))) for p in params])
    x0 = np.clip(x0, lower + 1e-9 * (upper - lower), upper - 1e-9 * (upper - lower))
    count = [0]

    def values_of(x: np.ndarray) -> dict[str, float]:
        return {p.name: p.from_internal(float(v)) for p, v in zip(params, x)}

    def fun(x: np.ndarray) -> np.ndarray:
        count[0] += 1
        return residual(values_of(x))

    result = least_squares(
        fun,
        x0,
        bounds=(lower, upper),
        diff_step=2e-3,
        x_scale="jac",
        max_nfev=max_evaluations,
        method="trf",
        ftol=rtol,
        xtol=rtol,
    )
    cost = float(result.fun @ result.fun)
    values = values_of(result.x)
    intervals = _intervals(params, result.x, result.jac, cost, len(result.fun), n_obs)
    return Fit(tuple(c.name for c in candidates), values, intervals, cost, n_obs, count[0])


def _intervals(
    params: list[Parameter], x: np.ndarray, jac: np.ndarray, cost: float, n_res: int, n_obs: int
) -> dict[str, tuple[float, float]]:
    dof = max(n_res - len(x), 1)
    # residual entries are correlated: scale the information to n_obs independent observations
    sigma2 = cost / dof
    info = jac.T @ jac * (n_obs / n_res)
    try:
        cov = sigma2 * (n_res / n_obs) * np.linalg.pinv(info)
    except np.linalg.LinAlgError:
        cov = np.full((len(x), len(x)), np.inf)
    out = {}
    for i, p in enumerate(params):
        half = 1.96 * math.sqrt(max(float(cov[i, i]), 0.0))
        lo, hi = x[i] - half, x[i] + half
        if p.log:
            out[p.name] = (math.exp(lo), math.exp(min(hi, 700.0)))
        else:
            out[p.name] = (lo, hi)
    return out


def fit_scalar(
    candidate: Candidate,
    cost: Callable[[float], float],
    n_obs: int,
    grid: np.ndarray | None = None,
    integer_step: float | None = None,
    max_refinements: int = 500,
) -> Fit:
    """One-parameter fit: a coarse grid then bounded Brent refinement between the best grid point's
    neighbours (at most ``max_refinements`` evaluations; or the grid alone for a parameter on steps of
    ``integer_step``, e.g. a delay in physics steps). Interval from the cost's curvature."""
    p = candidate.parameters[0]
    count = [0]

    def f(v: float) -> float:
        count[0] += 1
        return cost(v)

    if grid is None:
        grid = np.linspace(p.lower, p.upper, 25)
    costs = np.array([f(float(v)) for v in grid])
    best = int(np.argmin(costs))
    if integer_step is not None:
        value, best_cost = float(grid[best]), float(costs[best])
        half = integer_step
    else:
        lo, hi = grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]
        options = {"xatol": 1e-6 * (p.upper - p.lower), "maxiter": max_refinements}
        res = minimize_scalar(f, bounds=(lo, hi), method="bounded", options=options)
        value, best_cost = (
            (float(res.x), float(res.fun)) if res.fun < costs[best] else (float(grid[best]), float(costs[best]))
        )
        h = 1e-3 * (p.upper - p.lower)
        curvature = (f(min(value + h, p.upper)) - 2 * best_cost + f(max(value - h, p.lower))) / h**2
        sigma2 = best_cost / n_obs
        half = 1.96 * math.sqrt(2 * sigma2 / curvature) if curvature > 0 else math.inf
    return Fit((candidate.name,), {p.name: value}, {p.name: (value - half, value + half)}, best_cost, n_obs, count[0])
