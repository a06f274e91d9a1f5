"""Drift per course section: how much position error an estimate accumulates on each stretch of a course.

The sections are the contiguous runs of ticks whose ground-truth base position lies on the same course patch
(``Course.patch_at``: a patch name or "default"), in the order the robot crosses them; a patch crossed twice
gives two sections. The z drift of a section is the change of the (start-aligned) z error over it, measured
from the last tick of the previous section, so the sections' drifts add up to the final drift; divided by the
horizontal distance the ground truth travelled over the section it is a rate [m/m]. Constant memory per
section; no ROS.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

Locator = Callable[[float, float], str]


@dataclass
class Section:
    """One stretch of the course: name (patch), time span [s], start and end ground-truth x [m], horizontal
    distance travelled [m] and the position error [m] (estimate - truth, world) at its start and end."""

    name: str
    t_start_s: float
    t_end_s: float
    x_start_m: float
    x_end_m: float
    distance_m: float
    error_start_m: np.ndarray
    error_end_m: np.ndarray

    @property
    def drift_m(self) -> np.ndarray:
        """Error accumulated over the section [m] per world axis."""
        return self.error_end_m - self.error_start_m

    @property
    def z_drift_per_m(self) -> float:
        """z drift per metre travelled [m/m]; NaN over a section without horizontal travel."""
        return float(self.drift_m[2] / self.distance_m) if self.distance_m > 1e-6 else math.nan

    def as_dict(self, decimals: int = 4) -> dict[str, object]:
        rate = self.z_drift_per_m
        return {"name": self.name, "t_s": [round(self.t_start_s, 3), round(self.t_end_s, 3)],
                "x_m": [round(self.x_start_m, 3), round(self.x_end_m, 3)], "distance_m": round(self.distance_m, 4),
                "drift_m": np.round(self.drift_m, decimals).tolist(),
                "z_drift_per_m": None if math.isnan(rate) else round(rate, decimals)}


class SectionDrift:
    """Accumulates ``Section`` s from (t, truth position, position error) samples; ``locate(x, y)`` names the
    patch under a point (e.g. ``Course.patch_at``)."""

    def __init__(self, locate: Locator) -> None:
        self.locate = locate
        self.sections: list[Section] = []
        self._last: tuple[float, np.ndarray, np.ndarray] | None = None

    def add(self, t_s: float, truth_position: np.ndarray, error: np.ndarray) -> None:
        truth = np.asarray(truth_position, dtype=float)
        error = np.asarray(error, dtype=float)
        name = str(self.locate(float(truth[0]), float(truth[1])))
        current = self.sections[-1] if self.sections else None
        if current is None or current.name != name:
            # A section starts where the previous one ended (its last tick), so the drifts add up.
            t0, x0, e0 = (t_s, truth, error) if self._last is None else self._last
            current = Section(name, t0, t_s, float(x0[0]), float(truth[0]), 0.0, e0.copy(), error.copy())
            self.sections.append(current)
            if self._last is not None:
                current.distance_m += float(np.hypot(*(truth[:2] - x0[:2])))
        else:
            current.distance_m += float(np.hypot(*(truth[:2] - self._last[1][:2])))
        current.t_end_s, current.x_end_m, current.error_end_m = t_s, float(truth[0]), error.copy()
        self._last = (t_s, truth, error)

    def summary(self) -> list[dict[str, object]]:
        return [s.as_dict() for s in self.sections]


def format_section_table(sections: list[dict[str, object]]) -> list[str]:
    """Markdown lines of the per-section drift table (``SectionDrift.summary``)."""
    lines = ["| section | t [s] | x [m] | distance [m] | z drift [m] | z drift per m [m/m] | x drift [m] |",
             "|---|---|---|---|---|---|---|"]
    for s in sections:
        t0, t1 = s["t_s"]
        x0, x1 = s["x_m"]
        rate = s["z_drift_per_m"]
        lines.append(f"| {s['name']} | {t0:.1f} - {t1:.1f} | {x0:.2f} - {x1:.2f} | {s['distance_m']:.2f} | "
                     f"{s['drift_m'][2]:+.3f} | {'n/a' if rate is None else f'{rate:+.3f}'} | "
                     f"{s['drift_m'][0]:+.3f} |")
    return lines
