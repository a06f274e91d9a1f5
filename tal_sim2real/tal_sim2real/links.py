"""Extra mass on a leg's lower link, applied to a running PyBullet ``Simulation`` (issue 34 item 3: the mass
of a leg's link, per leg; the bridge's own effects are global).

The mass is a point mass at the link's centre of mass: the link's mass grows, its centre of mass and its
rotational inertia about it stay (PyBullet's ``changeDynamics(mass=...)`` alone would recompute the inertia
from the collision shape, so the URDF's inertia is set again with it). The lower link of a leg is the child
of the leg's last joint in the description's order (HAA, HFE, KFE: the shin), so nothing is HyQ-specific.
"""

from __future__ import annotations

import math

import numpy as np

from tal_core.legs import LEGS

from .errors import ModelConfigError


class LowerLinkMasses:
    """Sets the extra mass [kg] of each leg's lower link on ``sim`` (a ``tal_sim_bridge`` ``Simulation``)
    relative to the masses it had when this was made."""

    def __init__(self, sim) -> None:
        self.sim = sim
        joints_per_leg = len(sim.joint_ids) // len(LEGS)
        self.links = [sim.joint_ids[joints_per_leg * (i + 1) - 1] for i in range(len(LEGS))]
        info = [sim.client.getDynamicsInfo(sim.robot, link) for link in self.links]
        self.nominal_kg = np.array([float(i[0]) for i in info])
        self.inertia = [tuple(float(v) for v in i[2]) for i in info]
        self.extra_kg = np.zeros(len(LEGS))

    def apply(self, extra_kg) -> None:
        """Extra mass per leg [kg] (leg order LF, RF, LH, RH; may be negative down to -90% of the link)."""
        extra = np.asarray(extra_kg, dtype=float)
        if extra.shape != (len(LEGS),) or not np.all(np.isfinite(extra)):
            raise ModelConfigError(f"lower-link extra masses must be {len(LEGS)} finite numbers [kg], got {extra_kg!r}")
        if np.any(self.nominal_kg + extra < 0.1 * self.nominal_kg):
            raise ModelConfigError(
                f"lower-link extra masses {extra.tolist()} kg leave less than 10% of the links' "
                f"{self.nominal_kg.tolist()} kg"
            )
        for i, (link, inertia) in enumerate(zip(self.links, self.inertia)):
            if math.isclose(extra[i], self.extra_kg[i], abs_tol=1e-12):
                continue
            self.sim.client.changeDynamics(
                self.sim.robot, link, mass=float(self.nominal_kg[i] + extra[i]), localInertiaDiagonal=list(inertia)
            )
        self.extra_kg = extra.copy()
