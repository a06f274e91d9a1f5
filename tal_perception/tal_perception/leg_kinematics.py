"""Closed-form, vectorised leg kinematics (HAA-HFE-KFE legs) derived from the Pinocchio model.

Every number comes from the model: the HAA joint origin and axis, the HFE and KFE origins and axes and
the foot frame, all read at the zero configuration with the base at the world origin (so world = base
frame there), plus the joint limits of the robot YAML. Nothing is HyQ specific; the structure must be
the usual one (checked at construction, ``LegKinematicsError`` otherwise):

* HFE and KFE axes parallel (or anti-parallel) to each other and perpendicular to the HAA axis.

Geometry used (per leg). With ``h`` the HAA origin, ``u`` its axis, ``w`` the HFE axis and
``e2 = w x u``, a vector ``v`` in the HAA body has coordinates ``X = v.u``, ``Y = v.e2``, ``W = v.w``.
HFE and KFE rotate the foot in the (X, Y) plane (``W`` stays the lateral offset ``d``); HAA rotates
the (W, Y) pair about ``u``. Inverse kinematics inverts the HAA rotation first (two branches: the one
of the nominal pose is kept), then solves the planar two-link problem (two knee branches: the nominal
one is kept).

Frames and units: positions [m] in the BASE frame (x forward, y left, z up), joint angles [rad] in
the leg's HAA, HFE, KFE order. Arrays are vectorised over a leading batch dimension.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike, NDArray

from tal_core.legs import LEGS, Leg, PerLeg
from tal_core.robot_model import RobotModel
from tal_perception.errors import LegKinematicsError, PerceptionInputError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
_AXIS_TOLERANCE = 1e-6  # [-] |cos| tolerance for parallel / perpendicular axes


@dataclass(frozen=True)
class IkResult:
    """Inverse kinematics of a batch of N foot positions.

    joints (N, 3) [rad] HAA, HFE, KFE (NaN where unreachable); reachable (N,) the position lies in the
    leg's reach (with the reach margin); within_limits (N,) the joints respect the position limits (with
    the limit margin); feasible = reachable & within_limits.
    """

    joints: FloatArray | None
    reachable: BoolArray
    within_limits: BoolArray
    knee_xyz: FloatArray  # (3, N) [m] base frame, KFE joint origins as x, y, z rows (NaN where unreachable)
    hfe_xyz: FloatArray  # (3, N) [m] base frame, HFE joint origins as x, y, z rows (NaN where unreachable)

    @property
    def knee(self) -> FloatArray:
        """(N, 3) [m] base frame, KFE joint origins."""
        return self.knee_xyz.T

    @property
    def hfe(self) -> FloatArray:
        """(N, 3) [m] base frame, HFE joint origins."""
        return self.hfe_xyz.T

    @property
    def feasible(self) -> BoolArray:
        return self.reachable & self.within_limits


@dataclass(frozen=True)
class LegGeometry:
    """Constant geometry of one leg read from the model (base frame at zero joint angles) [m, rad]."""

    leg: Leg
    haa_origin: FloatArray  # (3,) h [m]
    haa_axis: FloatArray  # (3,) u, unit
    hfe_axis: FloatArray  # (3,) w, unit
    kfe_sign: float  # +1 if the KFE axis is w, -1 if it is -w
    hfe_xyw: FloatArray  # (3,) HFE origin - h in (X, Y, W) coordinates [m]
    knee_xyw: FloatArray  # (3,) KFE origin - h in (X, Y, W) [m]
    foot_xyw: FloatArray  # (3,) foot centre - h in (X, Y, W) [m]
    lower_rad: FloatArray  # (3,) joint position lower limits
    upper_rad: FloatArray  # (3,) joint position upper limits
    hip_branch: float  # sign of the foot's planar Y in the nominal pose
    knee_branch: float  # sign of the planar knee angle in the nominal pose

    @property
    def e2(self) -> FloatArray:
        return np.cross(self.hfe_axis, self.haa_axis)

    @property
    def thigh_2d(self) -> FloatArray:
        """(2,) HFE -> KFE in (X, Y) at zero angles [m]."""
        return self.knee_xyw[:2] - self.hfe_xyw[:2]

    @property
    def shin_2d(self) -> FloatArray:
        """(2,) KFE -> foot in (X, Y) at zero angles [m]."""
        return self.foot_xyw[:2] - self.knee_xyw[:2]

    @property
    def max_reach_m(self) -> float:
        """[m] HFE-to-foot distance in the (X, Y) plane with the leg stretched."""
        return float(np.linalg.norm(self.thigh_2d) + np.linalg.norm(self.shin_2d))


def _rot2(angle: FloatArray, vector: FloatArray) -> FloatArray:
    """Rotate 2D vectors (2,) or (..., 2) by ``angle`` (...) counter-clockwise; result (..., 2)."""
    c, s = np.cos(angle), np.sin(angle)
    x, y = vector[..., 0], vector[..., 1]
    return np.stack([c * x - s * y, s * x + c * y], axis=-1)


def _wrap(angle: FloatArray) -> FloatArray:
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


class LegKinematics:
    """Vectorised forward and inverse kinematics of the four legs of ``model``.

    ``reach_margin_m`` [m]: targets closer than this to full stretch (or full fold) count as
    unreachable; ``limit_margin_rad`` [rad]: joints closer than this to a position limit are infeasible.
    """

    def __init__(self, model: RobotModel, reach_margin_m: float = 0.0, limit_margin_rad: float = 0.0) -> None:
        if not (np.isfinite(reach_margin_m) and reach_margin_m >= 0.0):
            raise LegKinematicsError(f"reach_margin_m must be a finite value >= 0 [m], got {reach_margin_m!r}")
        if not (np.isfinite(limit_margin_rad) and limit_margin_rad >= 0.0):
            raise LegKinematicsError(f"limit_margin_rad must be a finite value >= 0 [rad], got {limit_margin_rad!r}")
        self.reach_margin_m = float(reach_margin_m)
        self.limit_margin_rad = float(limit_margin_rad)
        self.foot_radius_m = float(model.description.foot_radius_m)
        self.geometry: PerLeg[LegGeometry] = PerLeg.from_sequence([_read_leg(model, leg) for leg in LEGS])
        self._constants = tuple(
            _IkConstants.build(g, self.reach_margin_m, self.limit_margin_rad) for g in self.geometry
        )

    # -- forward -------------------------------------------------------------------------------------
    def forward(self, leg: Leg, joints: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(HFE origin, KFE origin, foot centre) [m], base frame, each (N, 3), for joints (N, 3) [rad]."""
        g = self.geometry[leg]
        q = np.asarray(joints, dtype=float)
        if q.ndim != 2 or q.shape[1] != 3:
            raise PerceptionInputError(f"leg {leg.name}: joints must have shape (N, 3), got {q.shape}")
        theta1, theta2 = q[:, 1], g.kfe_sign * q[:, 2]
        knee_2d = g.hfe_xyw[:2] + _rot2(theta1, g.thigh_2d)
        foot_2d = knee_2d + _rot2(theta1 + theta2, g.shin_2d)
        n = q.shape[0]
        hfe_2d = np.broadcast_to(g.hfe_xyw[:2], (n, 2))
        points = [
            self._to_base(g, q[:, 0], xy, np.full(n, w_coord))
            for xy, w_coord in ((hfe_2d, g.hfe_xyw[2]), (knee_2d, g.knee_xyw[2]), (foot_2d, g.foot_xyw[2]))
        ]
        return points[0], points[1], points[2]

    @staticmethod
    def _to_base(g: LegGeometry, q_haa: FloatArray, xy: FloatArray, w_coord: FloatArray) -> FloatArray:
        """Base-frame positions of points with HAA-body coordinates (X, Y) and W, after the HAA rotation."""
        c, s = np.cos(q_haa), np.sin(q_haa)
        w_rot = w_coord * c + xy[:, 1] * s
        y_rot = -w_coord * s + xy[:, 1] * c
        return g.haa_origin + xy[:, 0, None] * g.haa_axis + y_rot[:, None] * g.e2 + w_rot[:, None] * g.hfe_axis

    # -- inverse -------------------------------------------------------------------------------------
    def inverse(self, leg: Leg, foot_base: ArrayLike, with_joints: bool = True) -> IkResult:
        """Joint angles putting the foot centre at ``foot_base`` (N, 3) [m], base frame (nominal branch).

        The rotations are built from normalised dot and cross products, so the knee (KFE origin)
        positions and the joint-limit check need no trigonometry; only the joint angles themselves need
        atan2 (skipped with ``with_joints=False``, then ``IkResult.joints`` is None).
        """
        p = np.asarray(foot_base, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3:
            raise PerceptionInputError(f"leg {leg.name}: foot positions must have shape (N, 3), got {p.shape}")
        return self.inverse_xyz(leg, p[:, 0], p[:, 1], p[:, 2], with_joints)

    def inverse_xyz(self, leg: Leg, x: FloatArray, y: FloatArray, z: FloatArray, with_joints: bool = False) -> IkResult:
        """``inverse`` for foot positions given as three (N,) component arrays [m], base frame.

        The batch runs along the last axis of every intermediate array (numpy is an order of magnitude
        slower on (N, 3) arrays whose inner axis has 3 elements) and every constant is a Python float
        precomputed per leg (``_IkConstants``), which keeps the per-call overhead low.
        """
        c = self._constants[leg]
        solution = _solve(c, *_haa_frame(c, x, y, z))
        reachable = solution.reachable
        origins = solution.origins()
        knee = np.empty((3, reachable.shape[0]))  # (3, N), returned transposed
        hfe = np.empty((3, reachable.shape[0]))
        for i in range(3):
            knee[i] = origins.knee(i)
            hfe[i] = origins.hfe(i)
        if not reachable.all():
            knee[:, ~reachable] = np.nan
            hfe[:, ~reachable] = np.nan
        joints = None
        if with_joints:
            joints = np.arctan2(np.stack(solution.sines, axis=-1), np.stack(solution.cosines, axis=-1))
            joints[~reachable] = np.nan
        return IkResult(joints=joints, reachable=reachable, within_limits=solution.within, knee_xyz=knee, hfe_xyz=hfe)

    def within_limits_xyz(
        self, leg: Leg, x: FloatArray, y: FloatArray, z: FloatArray, cells: NDArray[np.intp] | None = None
    ) -> tuple[BoolArray, JointOrigins]:
        """Joint-limit check of foot positions given as three (N,) arrays [m], base frame, and the HFE and
        KFE origins of the M configurations within the limits only (in batch order).

        Same numbers as ``inverse_xyz`` (same operations, element by element), for callers that only
        look at feasible legs (the VPA's leg collision): the joint origins of the rejected targets are
        never built, and their base-frame rows are built one at a time, on demand (``JointOrigins``).
        With ``cells`` (N,), x and y are per-cell arrays (C,) and target k is (x[cells[k]], y[cells[k]],
        z[k]): the x and y terms of the change to the HAA frame are then summed once per cell (many
        targets share a cell: the VPA's hip heights).
        """
        c = self._constants[leg]
        if cells is not None:
            return self.within_limits_cells(leg, _cell_terms(c, x, y), z, cells)
        solution = _solve(c, *_haa_frame(c, x, y, z))
        return solution.within, solution.origins(np.flatnonzero(solution.within))

    def cell_terms(self, leg: Leg, x: FloatArray, y: FloatArray) -> CellTerms:
        """The per-cell part of ``within_limits_xyz(..., cells=)`` for cells at x, y (C,) [m], base frame:
        made once, reused by every batch of targets on these cells (``within_limits_cells``)."""
        return _cell_terms(self._constants[leg], x, y)

    def within_limits_cells(
        self, leg: Leg, terms: CellTerms, z: FloatArray, cells: NDArray[np.intp]
    ) -> tuple[BoolArray, JointOrigins]:
        """``within_limits_xyz(leg, x, y, z, cells=cells)`` with the cells' terms made beforehand by
        ``cell_terms(leg, x, y)`` (same numbers)."""
        solution = _solve(self._constants[leg], *_haa_frame_cells(self._constants[leg], terms, z, cells))
        return solution.within, solution.origins(np.flatnonzero(solution.within))


@dataclass(frozen=True, eq=False)
class CellTerms:
    """The x and y part [m] of the change to the HAA frame (``_haa_frame``) of foot targets above a few
    cells, per cell (C,): ``finite`` x and y finite, and the sums u0 x + u1 y, e2_0 x + e2_1 y,
    w0 x + w1 y of the coordinates relative to the HAA origin (0 where not finite)."""

    finite: BoolArray
    along_u: FloatArray
    along_e2: FloatArray
    along_w: FloatArray


@dataclass(frozen=True, eq=False)
class JointOrigins:
    """HFE and KFE joint origins of M leg configurations, kept in HAA-body coordinates [m] (X along the
    HAA axis u; e2 and w rotated by the HAA joint, see the module docstring).

    ``knee(i)`` / ``hfe(i)`` give base-frame coordinate i (0: x, 1: y, 2: z) [m] of all M origins, or of
    the entries ``select``; building one row at a time lets a caller skip the rows it does not need.
    """

    constants: _IkConstants
    knee_u: FloatArray  # (M,) KFE origin along u
    knee_e2: FloatArray  # (M,) KFE origin along e2
    knee_w: FloatArray  # (M,) KFE origin along w
    hfe_e2: FloatArray  # (M,) HFE origin along e2 (along u it is the constant hfe_x)
    hfe_w: FloatArray  # (M,) HFE origin along w

    def knee(self, axis: int, select: NDArray[np.intp] | slice = slice(None)) -> FloatArray:
        """(M,) or (len(select),) base-frame coordinate ``axis`` of the KFE origins [m]."""
        c, s = self.constants, select
        return c.h[axis] + self.knee_u[s] * c.u[axis] + self.knee_e2[s] * c.e2[axis] + self.knee_w[s] * c.w[axis]

    def hfe(self, axis: int, select: NDArray[np.intp] | slice = slice(None)) -> FloatArray:
        """(M,) or (len(select),) base-frame coordinate ``axis`` of the HFE origins [m]."""
        c, s = self.constants, select
        return (c.h[axis] + c.hfe_x * c.u[axis]) + self.hfe_e2[s] * c.e2[axis] + self.hfe_w[s] * c.w[axis]


@dataclass(frozen=True, eq=False)
class _IkSolution:
    """Cosines and sines (N,) of the HAA, HFE and KFE angles of a batch of targets, reachability and
    the joint-limit check (see ``LegKinematics.inverse_xyz``)."""

    constants: _IkConstants
    cosines: tuple[FloatArray, FloatArray, FloatArray]
    sines: tuple[FloatArray, FloatArray, FloatArray]
    reachable: BoolArray
    within: BoolArray

    def origins(self, select: NDArray[np.intp] | None = None) -> JointOrigins:
        """HFE and KFE origins of all configurations, or of the entries ``select``."""
        c = self.constants
        (cos_haa, cos_1, _), (sin_haa, sin_1, _) = self.cosines, self.sines
        if select is not None:
            cos_haa, sin_haa, cos_1, sin_1 = cos_haa[select], sin_haa[select], cos_1[select], sin_1[select]
        knee_x = c.hfe_x + cos_1 * c.thigh[0] - sin_1 * c.thigh[1]
        knee_y = c.hfe_y + sin_1 * c.thigh[0] + cos_1 * c.thigh[1]
        knee_e2 = knee_y * cos_haa - c.knee_w * sin_haa
        knee_w = knee_y * sin_haa + c.knee_w * cos_haa
        hfe_e2 = c.hfe_y * cos_haa - c.hfe_w * sin_haa
        hfe_w = c.hfe_y * sin_haa + c.hfe_w * cos_haa
        return JointOrigins(c, knee_x, knee_e2, knee_w, hfe_e2, hfe_w)


def _haa_frame(
    c: _IkConstants, x: FloatArray, y: FloatArray, z: FloatArray
) -> tuple[BoolArray, FloatArray, FloatArray, FloatArray]:
    """Foot targets [m] (base frame) relative to the HAA origin, along u, e2 and w: (finite, X, Y, W),
    each (N,); non-finite targets are moved to the origin (``finite`` False)."""
    u, e2, wa = c.u, c.e2, c.w
    finite = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
    rx, ry, rz = x - c.h[0], y - c.h[1], z - c.h[2]
    if not finite.all():
        rx, ry, rz = (np.where(finite, v, 0.0) for v in (rx, ry, rz))
    x_t = u[0] * rx + u[1] * ry + u[2] * rz
    y_t = e2[0] * rx + e2[1] * ry + e2[2] * rz
    w_t = wa[0] * rx + wa[1] * ry + wa[2] * rz
    return finite, x_t, y_t, w_t


def _cell_terms(c: _IkConstants, x: FloatArray, y: FloatArray) -> CellTerms:
    """``CellTerms`` of cells at x, y (C,) [m], base frame."""
    u, e2, wa = c.u, c.e2, c.w
    finite = np.isfinite(x) & np.isfinite(y)
    rx, ry = np.where(finite, x - c.h[0], 0.0), np.where(finite, y - c.h[1], 0.0)
    return CellTerms(finite, u[0] * rx + u[1] * ry, e2[0] * rx + e2[1] * ry, wa[0] * rx + wa[1] * ry)


def _haa_frame_cells(
    c: _IkConstants, terms: CellTerms, z: FloatArray, cells: NDArray[np.intp]
) -> tuple[BoolArray, FloatArray, FloatArray, FloatArray]:
    """``_haa_frame`` of targets (N,) above ``cells`` (N,) at heights z (N,) [m]: the per-cell x and y
    terms are gathered and the z term added (X, Y, W of finite targets are the same sums in the same
    order, so the same numbers)."""
    finite = terms.finite[cells] & np.isfinite(z)
    rz = z - c.h[2]
    if not finite.all():
        rz = np.where(finite, rz, 0.0)
    x_t = terms.along_u[cells] + c.u[2] * rz
    y_t = terms.along_e2[cells] + c.e2[2] * rz
    w_t = terms.along_w[cells] + c.w[2] * rz
    return finite, x_t, y_t, w_t


def _solve(c: _IkConstants, finite: BoolArray, x_t: FloatArray, y_t: FloatArray, w_t: FloatArray) -> _IkSolution:
    """Closed-form IK (nominal branches) of foot targets (N,) given in the HAA frame (``_haa_frame``):
    joint cosines and sines, reachability (with the reach margin) and the joint-limit check (with the
    limit margin).

    The formulas of ``_solve_reference`` (the readable form), evaluated operation by operation in the
    same order but into fewer, reused arrays (``out=``): the same IEEE operations on the same operands,
    so the same bits (tested), with half the temporary arrays (this runs on ~300,000 targets per VPA
    update).
    """
    d = c.d
    tmp = np.empty_like(x_t)
    # HAA angle: from (d, y_p) (foot in the unrotated HAA body) to (w_t, y_t), both of norm rho.
    rho_sq = np.multiply(w_t, w_t)
    rho_sq += np.multiply(y_t, y_t, out=tmp)  # w_t * w_t + y_t * y_t
    y_p = np.subtract(rho_sq, d * d)
    np.sqrt(np.maximum(y_p, 0.0, out=y_p), out=y_p)
    if c.hip_branch < 0.0:
        np.negative(y_p, out=y_p)
    inv_rho_sq = np.maximum(rho_sq, 1e-12)
    np.divide(1.0, inv_rho_sq, out=inv_rho_sq)
    cos_haa = np.multiply(w_t, d)
    cos_haa += np.multiply(y_p, y_t, out=tmp)  # d * w_t + y_p * y_t
    cos_haa *= inv_rho_sq
    sin_haa = np.multiply(y_p, w_t)
    sin_haa -= np.multiply(y_t, d, out=tmp)  # y_p * w_t - d * y_t
    sin_haa *= inv_rho_sq
    # Planar two-link problem from HFE to the foot.
    tx, ty = np.subtract(x_t, c.hfe_x), np.subtract(y_p, c.hfe_y)
    dist_sq = np.multiply(tx, tx)
    dist_sq += np.multiply(ty, ty, out=tmp)  # tx * tx + ty * ty
    cos_gamma = np.subtract(dist_sq, c.l_sq_sum)
    cos_gamma *= c.inv_2l1l2
    np.clip(cos_gamma, -1.0, 1.0, out=cos_gamma)
    sin_gamma = np.multiply(cos_gamma, cos_gamma)
    np.sqrt(np.subtract(1.0, sin_gamma, out=sin_gamma), out=sin_gamma)
    if c.knee_branch < 0.0:
        np.negative(sin_gamma, out=sin_gamma)
    # The shin, rotated by the knee, is the thigh direction rotated by gamma and scaled to l2.
    sx = np.multiply(cos_gamma, c.l2_ux)
    sx -= np.multiply(sin_gamma, c.l2_uy, out=tmp)  # l2_ux * cos_gamma - l2_uy * sin_gamma
    sy = np.multiply(sin_gamma, c.l2_ux)
    sy += np.multiply(cos_gamma, c.l2_uy, out=tmp)  # l2_ux * sin_gamma + l2_uy * cos_gamma
    cos_2 = np.multiply(sx, c.shin[0])  # KFE rotation: shin -> rotated shin
    cos_2 += np.multiply(sy, c.shin[1], out=tmp)
    cos_2 *= c.inv_l2_sq
    sin_2 = np.multiply(sy, c.shin[0])
    sin_2 -= np.multiply(sx, c.shin[1], out=tmp)
    sin_2 *= c.inv_l2_sq * c.kfe_sign
    rx2, ry2 = np.add(sx, c.thigh[0], out=sx), np.add(sy, c.thigh[1], out=sy)  # HFE -> foot at theta1 = 0
    inv_dist_sq = np.maximum(dist_sq, 1e-12)
    np.divide(1.0, inv_dist_sq, out=inv_dist_sq)
    cos_1 = np.multiply(rx2, tx)
    cos_1 += np.multiply(ry2, ty, out=tmp)  # rx2 * tx + ry2 * ty
    cos_1 *= inv_dist_sq
    sin_1 = np.multiply(rx2, ty)
    sin_1 -= np.multiply(ry2, tx, out=tmp)  # rx2 * ty - ry2 * tx
    sin_1 *= inv_dist_sq
    cosines, sines = (cos_haa, cos_1, cos_2), (sin_haa, sin_1, sin_2)
    reachable = np.greater_equal(rho_sq, d * d)
    reachable &= finite
    flag = np.less_equal(dist_sq, c.max_dist_sq)
    reachable &= flag
    reachable &= np.greater_equal(dist_sq, c.min_dist_sq, out=flag)
    # q in [lower + m, upper - m]  <=>  cos(q - mid) >= cos(half - m): no atan2 needed.
    within = reachable.copy() if c.limits_nonempty else np.zeros_like(reachable)
    for i in range(3):
        np.multiply(cosines[i], c.cos_mid[i], out=tmp)
        tmp += np.multiply(sines[i], c.sin_mid[i], out=rx2)  # rx2 is free once sin_1 is made
        within &= np.greater_equal(tmp, c.cos_half[i], out=flag)
    return _IkSolution(c, cosines, sines, reachable, within)


def _solve_reference(
    c: _IkConstants, finite: BoolArray, x_t: FloatArray, y_t: FloatArray, w_t: FloatArray
) -> _IkSolution:
    """``_solve`` written as plain expressions: the readable form, whose bits ``_solve`` must give."""
    d = c.d
    rho_sq = w_t * w_t + y_t * y_t
    y_p = np.sqrt(np.maximum(rho_sq - d * d, 0.0))
    if c.hip_branch < 0.0:
        y_p = -y_p
    # HAA angle: from (d, y_p) (foot in the unrotated HAA body) to (w_t, y_t), both of norm rho.
    inv_rho_sq = 1.0 / np.maximum(rho_sq, 1e-12)
    cos_haa = (d * w_t + y_p * y_t) * inv_rho_sq
    sin_haa = (y_p * w_t - d * y_t) * inv_rho_sq
    # Planar two-link problem from HFE to the foot.
    tx, ty = x_t - c.hfe_x, y_p - c.hfe_y
    dist_sq = tx * tx + ty * ty
    cos_gamma = np.clip((dist_sq - c.l_sq_sum) * c.inv_2l1l2, -1.0, 1.0)
    sin_gamma = np.sqrt(1.0 - cos_gamma * cos_gamma)
    if c.knee_branch < 0.0:
        sin_gamma = -sin_gamma
    # The shin, rotated by the knee, is the thigh direction rotated by gamma and scaled to l2.
    sx = c.l2_ux * cos_gamma - c.l2_uy * sin_gamma
    sy = c.l2_ux * sin_gamma + c.l2_uy * cos_gamma
    rx2, ry2 = sx + c.thigh[0], sy + c.thigh[1]  # HFE -> foot at theta1 = 0
    inv_dist_sq = 1.0 / np.maximum(dist_sq, 1e-12)
    cos_1 = (rx2 * tx + ry2 * ty) * inv_dist_sq
    sin_1 = (rx2 * ty - ry2 * tx) * inv_dist_sq
    cos_2 = (c.shin[0] * sx + c.shin[1] * sy) * c.inv_l2_sq  # KFE rotation: shin -> rotated shin
    sin_2 = (c.shin[0] * sy - c.shin[1] * sx) * (c.inv_l2_sq * c.kfe_sign)
    cosines, sines = (cos_haa, cos_1, cos_2), (sin_haa, sin_1, sin_2)
    reachable = finite & (rho_sq >= d * d) & (dist_sq <= c.max_dist_sq) & (dist_sq >= c.min_dist_sq)
    # q in [lower + m, upper - m]  <=>  cos(q - mid) >= cos(half - m): no atan2 needed.
    within = reachable.copy() if c.limits_nonempty else np.zeros_like(reachable)
    for i in range(3):
        within &= cosines[i] * c.cos_mid[i] + sines[i] * c.sin_mid[i] >= c.cos_half[i]
    return _IkSolution(c, cosines, sines, reachable, within)


@dataclass(frozen=True)
class _IkConstants:
    """Per-leg constants of the inverse kinematics as Python floats (see ``LegGeometry``)."""

    h: tuple[float, float, float]
    u: tuple[float, float, float]
    e2: tuple[float, float, float]
    w: tuple[float, float, float]
    d: float
    hfe_x: float
    hfe_y: float
    hfe_w: float
    knee_w: float
    thigh: tuple[float, float]
    shin: tuple[float, float]
    l2_ux: float
    l2_uy: float
    l_sq_sum: float
    inv_2l1l2: float
    inv_l2_sq: float
    kfe_sign: float
    hip_branch: float
    knee_branch: float
    max_dist_sq: float
    min_dist_sq: float
    cos_mid: tuple[float, float, float]
    sin_mid: tuple[float, float, float]
    cos_half: tuple[float, float, float]
    limits_nonempty: bool

    @classmethod
    def build(cls, g: LegGeometry, reach_margin_m: float, limit_margin_rad: float) -> _IkConstants:
        def floats(values: ArrayLike) -> tuple[float, ...]:
            return tuple(float(v) for v in np.asarray(values).reshape(-1))

        thigh, shin = g.thigh_2d, g.shin_2d
        l1, l2 = float(np.hypot(*thigh)), float(np.hypot(*shin))
        max_dist = max(l1 + l2 - reach_margin_m, 0.0)
        min_dist = abs(l1 - l2) + reach_margin_m
        mid = 0.5 * (g.lower_rad + g.upper_rad)
        half = 0.5 * (g.upper_rad - g.lower_rad) - limit_margin_rad
        return cls(
            h=floats(g.haa_origin), u=floats(g.haa_axis), e2=floats(g.e2), w=floats(g.hfe_axis),
            d=float(g.foot_xyw[2]), hfe_x=float(g.hfe_xyw[0]), hfe_y=float(g.hfe_xyw[1]), hfe_w=float(g.hfe_xyw[2]),
            knee_w=float(g.knee_xyw[2]), thigh=floats(thigh), shin=floats(shin),
            l2_ux=l2 * float(thigh[0]) / l1, l2_uy=l2 * float(thigh[1]) / l1,
            l_sq_sum=l1 * l1 + l2 * l2, inv_2l1l2=1.0 / (2.0 * l1 * l2), inv_l2_sq=1.0 / (l2 * l2),
            kfe_sign=g.kfe_sign, hip_branch=g.hip_branch, knee_branch=g.knee_branch,
            max_dist_sq=max_dist * max_dist, min_dist_sq=min_dist * min_dist,
            cos_mid=floats(np.cos(mid)), sin_mid=floats(np.sin(mid)),
            cos_half=floats(np.cos(np.maximum(half, 0.0))), limits_nonempty=bool((half >= 0.0).all()),
        )  # fmt: skip


def _read_leg(model: RobotModel, leg: Leg) -> LegGeometry:
    """Read one leg's geometry from Pinocchio at the zero configuration (base at the world origin)."""
    pin_model, data = model.model, model.model.createData()
    description = model.description
    q0 = pin.neutral(pin_model)
    pin.computeJointJacobians(pin_model, data, q0)
    pin.framesForwardKinematics(pin_model, data, q0)
    names = description.leg_joint_names(leg)
    origins, axes = [], []
    for name in names:
        joint_id = pin_model.getJointId(name)
        jacobian = pin.getJointJacobian(pin_model, data, joint_id, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        axis = jacobian[3:, pin_model.joints[joint_id].idx_v]
        if not np.isclose(np.linalg.norm(axis), 1.0, atol=_AXIS_TOLERANCE):
            raise LegKinematicsError(f"leg {leg.name}: joint {name!r} is not a revolute joint")
        origins.append(data.oMi[joint_id].translation.copy())
        axes.append(axis / np.linalg.norm(axis))
    foot = data.oMf[pin_model.getFrameId(description.foot_frames[leg])].translation.copy()
    u, w, w_knee = axes
    if abs(float(u @ w)) > _AXIS_TOLERANCE:
        raise LegKinematicsError(f"leg {leg.name}: HFE axis is not perpendicular to the HAA axis (u.w = {u @ w:.3g})")
    if abs(abs(float(w @ w_knee)) - 1.0) > _AXIS_TOLERANCE:
        raise LegKinematicsError(
            f"leg {leg.name}: KFE axis is not parallel to the HFE axis (w.w_kfe = {w @ w_knee:.3g})"
        )
    e2 = np.cross(w, u)
    h = origins[0]

    def xyw(point: FloatArray) -> FloatArray:
        v = point - h
        return np.array([v @ u, v @ e2, v @ w])

    hfe, knee, foot_xyw = xyw(origins[1]), xyw(origins[2]), xyw(foot)
    sl = description.leg_joint_slice(leg)
    nominal = np.asarray(description.nominal_joint_positions_rad, dtype=float)[sl]
    kfe_sign = float(np.sign(w @ w_knee))
    partial = LegGeometry(
        leg, h, u, w, kfe_sign, hfe, knee, foot_xyw,
        np.asarray(description.position_lower_rad, dtype=float)[sl].copy(),
        np.asarray(description.position_upper_rad, dtype=float)[sl].copy(),
        1.0, 1.0,
    )  # fmt: skip
    # Branches of the nominal pose: sign of the planar foot Y and of the knee angle.
    thigh, shin = partial.thigh_2d, partial.shin_2d
    theta1, theta2 = nominal[1], kfe_sign * nominal[2]
    foot_2d = hfe[:2] + _rot2(np.array(theta1), thigh) + _rot2(np.array(theta1 + theta2), shin)
    gamma = _wrap(theta2 + np.arctan2(shin[1], shin[0]) - np.arctan2(thigh[1], thigh[0]))
    hip_branch = 1.0 if foot_2d[1] >= 0.0 else -1.0
    knee_branch = 1.0 if gamma >= 0.0 else -1.0
    return LegGeometry(
        leg, h, u, w, kfe_sign, hfe, knee, foot_xyw, partial.lower_rad, partial.upper_rad, hip_branch, knee_branch
    )
