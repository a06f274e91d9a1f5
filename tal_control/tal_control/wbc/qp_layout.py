"""Fixed layout of the whole-body QP: variable blocks, constraint rows and sparsity patterns.

The QP always carries forces and slacks for all four legs, so its sparsity pattern never changes when
legs switch between stance and swing: OSQP is set up once and then only updated (values and bounds),
which keeps its factorisation pattern and lets it warm-start from the previous cycle. A swing leg's
forces are pinned to zero by its friction rows, a stance leg's slacks by its slack rows.

Variables  u = [qdd (nv) | F (3 per leg, world frame) | eta (3 per leg) | eps (3 per leg, c3WBC only)]
Rows       dynamics (6) | task-low (3/leg) | task-high (3/leg) | friction (5/leg) | torque (nj) |
           joint acceleration (nj) | slack bounds (3/leg) | c3 rows (compliant model only)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from tal_core.legs import NUM_LEGS

INF = 1e30  # OSQP and DAQP treat bounds at or beyond 1e30 as infinite
FRICTION_ROWS_PER_LEG = 5


@dataclass(frozen=True)
class QpLayout:
    """Index bookkeeping of the QP for a robot with ``nv`` velocity coordinates and ``nj`` joints."""

    nv: int
    nj: int
    leg_joint_v_indices: tuple[tuple[int, ...], ...]  # per leg: indices into v of its joints
    compliant: bool = False

    # -- variable blocks -------------------------------------------------------------------------------
    @property
    def n_force(self) -> int:
        return 3 * NUM_LEGS

    @property
    def qdd(self) -> slice:
        return slice(0, self.nv)

    @property
    def force(self) -> slice:
        return slice(self.nv, self.nv + self.n_force)

    @property
    def slack(self) -> slice:
        start = self.nv + self.n_force
        return slice(start, start + self.n_force)

    @property
    def penetration(self) -> slice:
        start = self.nv + 2 * self.n_force
        return slice(start, start + (self.n_force if self.compliant else 0))

    @property
    def n_vars(self) -> int:
        return self.nv + (3 if self.compliant else 2) * self.n_force

    def leg_cols(self, block: slice, leg: int) -> slice:
        return slice(block.start + 3 * leg, block.start + 3 * leg + 3)

    # -- constraint rows -------------------------------------------------------------------------------
    @property
    def dynamics_rows(self) -> slice:
        return slice(0, 6)

    @property
    def task_low_rows(self) -> slice:
        return slice(6, 6 + self.n_force)

    @property
    def task_high_rows(self) -> slice:
        start = self.task_low_rows.stop
        return slice(start, start + self.n_force)

    @property
    def friction_rows(self) -> slice:
        start = self.task_high_rows.stop
        return slice(start, start + FRICTION_ROWS_PER_LEG * NUM_LEGS)

    @property
    def torque_rows(self) -> slice:
        start = self.friction_rows.stop
        return slice(start, start + self.nj)

    @property
    def joint_acc_rows(self) -> slice:
        start = self.torque_rows.stop
        return slice(start, start + self.nj)

    @property
    def slack_rows(self) -> slice:
        start = self.joint_acc_rows.stop
        return slice(start, start + self.n_force)

    @property
    def compliant_rows(self) -> slice:
        """c3WBC rows (3 per leg each): force model F = K eps + D deps, and eps >= 0."""
        start = self.slack_rows.stop
        return slice(start, start + (2 * self.n_force if self.compliant else 0))

    @property
    def n_rows(self) -> int:
        return self.compliant_rows.stop

    # -- structural sparsity ---------------------------------------------------------------------------
    def foot_jacobian_mask(self, leg: int) -> np.ndarray:
        """(3, nv) structural non-zeros of a foot Jacobian: the 6 base columns and the leg's joints."""
        mask = np.zeros((3, self.nv), dtype=bool)
        mask[:, :6] = True
        mask[:, list(self.leg_joint_v_indices[leg])] = True
        return mask

    def constraint_mask(self) -> np.ndarray:
        """(n_rows, n_vars) structural non-zeros of the constraint matrix."""
        mask = np.zeros((self.n_rows, self.n_vars), dtype=bool)
        mask[self.dynamics_rows, self.qdd] = True
        mask[self.dynamics_rows, self.force] = True
        for leg in range(NUM_LEGS):
            rows = slice(3 * leg, 3 * leg + 3)
            jac = self.foot_jacobian_mask(leg)
            for block in (self.task_low_rows, self.task_high_rows):
                block_rows = slice(block.start + rows.start, block.start + rows.stop)
                mask[block_rows, self.qdd] = jac
                mask[block_rows, self.leg_cols(self.slack, leg)] = np.eye(3, dtype=bool)
            friction = slice(self.friction_rows.start + FRICTION_ROWS_PER_LEG * leg,
                             self.friction_rows.start + FRICTION_ROWS_PER_LEG * (leg + 1))
            mask[friction, self.leg_cols(self.force, leg)] = True
            torque_rows = np.arange(self.torque_rows.start, self.torque_rows.stop)
            joint_rows = [torque_rows[j - 6] for j in self.leg_joint_v_indices[leg]]
            mask[np.ix_(joint_rows, range(self.leg_cols(self.force, leg).start,
                                          self.leg_cols(self.force, leg).stop))] = True
            if self.compliant:
                model_rows = slice(self.compliant_rows.start + 3 * leg, self.compliant_rows.start + 3 * leg + 3)
                mask[model_rows, self.leg_cols(self.force, leg)] = np.eye(3, dtype=bool)
                mask[model_rows, self.leg_cols(self.penetration, leg)] = True
                # Penetration in the contact frame: rows (n, t1, t2) . eps, so a full 3x3 block.
                bound_rows = slice(self.compliant_rows.start + self.n_force + 3 * leg,
                                   self.compliant_rows.start + self.n_force + 3 * leg + 3)
                mask[bound_rows, self.leg_cols(self.penetration, leg)] = True
                # c3 stance task: J qdd + eps_k / dt^2 = ... lives in the task rows (diagonal block).
                for block in (self.task_low_rows, self.task_high_rows):
                    block_rows = slice(block.start + 3 * leg, block.start + 3 * leg + 3)
                    mask[block_rows, self.leg_cols(self.penetration, leg)] = np.eye(3, dtype=bool)
        mask[self.torque_rows, self.qdd] = True
        mask[self.joint_acc_rows, slice(6, self.nv)] = np.eye(self.nj, dtype=bool)
        mask[self.slack_rows, self.slack] = np.eye(self.n_force, dtype=bool)
        return mask

    def cost_mask(self) -> np.ndarray:
        """(n_vars, n_vars) structural non-zeros of the (symmetric) cost Hessian."""
        mask = np.eye(self.n_vars, dtype=bool)
        mask[self.force, self.force] = True
        return mask


class FixedPatternMatrix:
    """A sparse CSC matrix with a fixed pattern whose values are refreshed from a dense array."""

    def __init__(self, mask: np.ndarray, upper_triangular: bool = False) -> None:
        if upper_triangular:
            mask = np.triu(mask)
        pattern = sp.csc_matrix(mask.astype(float))
        pattern.sort_indices()
        coo = pattern.tocoo()
        # CSC stores entries column by column; recover (row, col) in that order.
        order = np.lexsort((coo.row, coo.col))
        self.rows = coo.row[order]
        self.cols = coo.col[order]
        self.shape = mask.shape
        self.matrix = sp.csc_matrix((np.zeros(len(self.rows)), (self.rows, self.cols)), shape=self.shape)
        self.matrix.sort_indices()

    def values_from(self, dense: np.ndarray) -> np.ndarray:
        """The CSC data vector of ``dense`` restricted to the pattern (entries outside it are ignored)."""
        return np.ascontiguousarray(dense[self.rows, self.cols])

    def with_values(self, values: np.ndarray) -> sp.csc_matrix:
        matrix = self.matrix.copy()
        matrix.data = values.copy()
        return matrix
