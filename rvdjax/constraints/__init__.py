"""Constraint library: named blocks of stage-wise rows for :class:`rvdjax.ocp.OCP` (DESIGN §2).

Every builder returns a :class:`Block`: a name, the rows ``F (N, m, n)``, ``f (N, m)`` meaning
``F[t] @ v_t <= f[t]``, a penalty ``rho (N, m)``, a 0/1 ``mask (N, m)`` and two static labels:

* ``acts_on``: ``"x"`` (state rows, on the *predicted* state x_{t+1}; soft in the OCP, exact L1
  penalty rho) or ``"u"`` (input rows on u_t; hard);
* ``kind``: ``"hard"`` (a constraint of the paper: a plan that violates it makes the solve
  INFEASIBLE, a truth that violates it counts in ``max_violation_m``), ``"penalty"`` (an
  external penalty of the paper, e.g. the approach-cone term lambda 1^T (H x)_+: its "violation"
  is cost, never a failure) or ``"monitor"`` (a truth margin that is reported but not judged,
  e.g. the docking cone during the entry transient).

A family's OCP is its dynamics, its cost and :func:`stack` of its blocks; the closed loop judges
the truth with :func:`margins` of blocks built by the same builders at the truth's own time and
state, so no row order is kept by hand anywhere.

Rows have unit normals (planes, cones, velocity bounds; keep-out zones as the tangent plane with
a unit normal), so a row's slack ``f - F v`` is a distance in metres (m/s for velocity rows) and
``rho`` is a penalty per metre of violation. The position part of the state is selected by
``pos_index`` (static tuple of ints, default ``(0, .., d-1)``; for the planar 3-DOF state
(x, y, theta, vx, vy, omega) use ``(0, 1)``), the velocity part by ``vel_index``. Units:
metres, seconds, radians (angles anticlockwise from the first position axis).

All builders are pure JAX (static shapes, no Python control flow on traced values): jit, vmap
and grad apply. Static arguments (half angles, face counts) are range-checked when they are
concrete numbers (ValueError naming the parameter); JAX tracers are not checked.
"""

from __future__ import annotations

from rvdjax.constraints.blocks import Block, block_margin, exclusive, hard_mask, margins, stack
from rvdjax.constraints.rows import (
    approach_cone,
    approach_cone_penalty,
    between_samples,
    cost_rows,
    ellipsoid_keep_out,
    entry_cone,
    holding_radius,
    holding_radius_update,
    keep_out_plane,
    overshoot,
    rotating_hyperplane,
    sphere_keep_out,
    thrust_box,
    velocity_bound,
)

__all__ = [
    "Block",
    "stack",
    "exclusive",
    "margins",
    "block_margin",
    "hard_mask",
    "thrust_box",
    "ellipsoid_keep_out",
    "sphere_keep_out",
    "holding_radius",
    "holding_radius_update",
    "entry_cone",
    "approach_cone",
    "approach_cone_penalty",
    "keep_out_plane",
    "rotating_hyperplane",
    "overshoot",
    "velocity_bound",
    "cost_rows",
    "between_samples",
]
