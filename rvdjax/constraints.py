"""Constraint library: stage-wise rows for :class:`rvdjax.ocp.OCP` (DESIGN §2).

Every builder returns arrays with a leading stage axis N that drop into the OCP fields:

* state rows ``Fx (N, m, nx)``, ``fx (N, m)`` meaning ``Fx[t] @ x_{t+1} <= fx[t]`` (soft rows
  with exact L1 penalty ``rho`` in the OCP), stage t acting on the *predicted* state x_{t+1};
* input rows ``Fu (N, m, nu)``, ``fu (N, m)`` meaning ``Fu[t] @ u_t <= fu[t]`` (hard rows).

The position part of the state is selected by ``pos_index`` (static tuple of ints, default
``(0, .., d-1)``; for the planar 3-DOF state (x, y, theta, vx, vy, omega) use ``(0, 1)``), the
velocity part by ``vel_index``. Units: metres, seconds, radians (angles measured
anticlockwise from the first position axis).

All builders are pure JAX (no Python control flow on traced values, static shapes), so they
can be jitted, vmapped and differentiated. Static arguments (half angles, gains, bounds) are
range-checked when they are concrete Python/NumPy numbers (ValueError naming the parameter);
JAX tracers are not checked.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "approach_cone_penalty_rows",
    "approach_cone_rows_3d",
    "ellipsoid_keepout_rows",
    "entry_cone_rows",
    "hold_point",
    "holding_radius_rows",
    "holding_radius_update",
    "hyperplane_angles",
    "overshoot_row",
    "rotating_hyperplane_rows",
    "stack_rows",
    "target_angles",
    "target_frame",
    "thrust_box_rows",
    "velocity_bound_rows",
]


# --------------------------------------------------------------------------- helpers


def _concrete(x) -> bool:
    """True when ``x`` holds concrete values (not a JAX tracer) and can be range-checked."""
    if isinstance(x, jax.core.Tracer):
        return False
    if isinstance(x, (list, tuple)):
        return all(_concrete(v) for v in x)
    return True


def _check(name: str, x, lo=None, hi=None, lo_open=True, hi_open=True) -> None:
    """Raise ValueError unless every entry of concrete ``x`` is finite and within (lo, hi)."""
    if x is None or not _concrete(x):
        return
    a = np.asarray(x, dtype=float)
    ok = np.all(np.isfinite(a))
    if lo is not None:
        ok = ok and np.all(a > lo if lo_open else a >= lo)
    if hi is not None:
        ok = ok and np.all(a < hi if hi_open else a <= hi)
    if not ok:
        lb = "-inf" if lo is None else f"{lo:g}"
        ub = "inf" if hi is None else f"{hi:g}"
        rng = f"{'(' if lo_open else '['}{lb}, {ub}{')' if hi_open else ']'}"
        raise ValueError(f"{name} must be finite and in {rng}, got {x!r}")


def _check_index(name: str, index, nx: int) -> tuple[int, ...]:
    index = tuple(int(i) for i in index)
    if not index or any(i < 0 or i >= nx for i in index) or len(set(index)) != len(index):
        raise ValueError(f"{name} must be distinct ints in [0, {nx}), got {index!r}")
    return index


def _pos_index(pos_index, d: int, nx: int) -> tuple[int, ...]:
    if not isinstance(nx, (int, np.integer)) or nx < d:
        raise ValueError(f"nx (state dimension) must be an int >= {d}, got {nx!r}")
    idx = tuple(range(d)) if pos_index is None else pos_index
    idx = _check_index("pos_index", idx, nx)
    if len(idx) != d:
        raise ValueError(f"pos_index must have {d} entries (position dimension), got {idx!r}")
    return idx


def _embed(a, nx: int, index: tuple[int, ...]):
    """Scatter the last axis of ``a`` (len(index)) into state columns ``index`` of width nx."""
    a = jnp.asarray(a)
    return jnp.zeros((*a.shape[:-1], nx), a.dtype).at[..., jnp.array(index)].set(a)


def _unit2(angle):
    angle = jnp.asarray(angle, dtype=float)
    return jnp.stack([jnp.cos(angle), jnp.sin(angle)], axis=-1)


def _safe_normalise(v, fallback):
    n2 = jnp.sum(v * v, axis=-1, keepdims=True)
    ok = n2 > 1e-24
    return jnp.where(ok, v / jnp.sqrt(jnp.where(ok, n2, 1.0)), fallback)


def _wrap(a):
    """Wrap angles to [-pi, pi)."""
    return (a + jnp.pi) % (2 * jnp.pi) - jnp.pi


# --------------------------------------------------------------------------- input rows


def thrust_box_rows(u_max, N: int, nu: int | None = None):
    """Thrust / torque box |u_i| <= u_max on every stage (paper 000 Eq. 5).

    Rows ``[I; -I] u_t <= [u_max; u_max]`` acting on the input u_t (hard input rows).

    Args:
        u_max: scalar or (nu,) bounds [N or N m, or m/s^2 for normalised models], > 0.
        N: horizon length (static int >= 1).
        nu: number of inputs; required when ``u_max`` is a scalar.

    Returns:
        (Fu (N, 2 nu, nu), fu (N, 2 nu)).
    """
    if not isinstance(N, (int, np.integer)) or N < 1:
        raise ValueError(f"N (horizon) must be an int >= 1, got {N!r}")
    _check("u_max", u_max, lo=0.0)
    u_max = jnp.asarray(u_max, dtype=float)
    if u_max.ndim == 0:
        if nu is None:
            raise ValueError("nu must be given when u_max is a scalar")
        u_max = jnp.broadcast_to(u_max, (nu,))
    nu = u_max.shape[0]
    eye = jnp.eye(nu)
    Fu = jnp.broadcast_to(jnp.concatenate([eye, -eye]), (N, 2 * nu, nu))
    fu = jnp.broadcast_to(jnp.concatenate([u_max, u_max]), (N, 2 * nu))
    return Fu, fu


# --------------------------------------------------------------------------- keep-out rows


def ellipsoid_keepout_rows(p_guess, centres, S, nx: int, pos_index=None):
    """Linearised ellipsoidal keep-out zone (paper 000 Eqs. 6-8 and 12).

    Keep-out set: (r - o)^T S (r - o) < 1 (S symmetric positive definite [1/m^2]). The
    expansion point is the boundary point on the segment from the centre o to the guessed
    position p (previous plan), r0 = o + (p - o) / sqrt((p - o)^T S (p - o)), and Eq. 7 is
    expanded about r0 (the paper's correction: r0, not r_obj). With E = (r0 - o)^T S, Eq. 8
    ``1 <= 2 E (r - o) - E (r0 - o)`` is the row (Eq. 12)

        -2 E r <= -1 - E (r0 + o).

    The row is tangent to the ellipsoid at r0 (equality there) and, since the quadratic is
    convex, its feasible half-space lies entirely outside the keep-out zone. If p == o the
    expansion direction falls back to the first position axis.

    Args:
        p_guess: (N, d) guessed chaser positions at stages t (for x_{t+1}) [m].
        centres: (N, d) obstacle centres at the same instants [m].
        S: (d, d) or (N, d, d) shape matrix [1/m^2]; a sphere of radius R has S = I / R^2.
        nx: state dimension.
        pos_index: static tuple of the d position columns of the state (default first d).

    Returns:
        (Fx (N, 1, nx), fx (N, 1)) state rows Fx x_{t+1} <= fx.
    """
    p_guess = jnp.asarray(p_guess, dtype=float)
    centres = jnp.asarray(centres, dtype=float)
    N, d = p_guess.shape
    idx = _pos_index(pos_index, d, nx)
    if _concrete(S):
        Sn = np.asarray(S, dtype=float)
        if Sn.shape not in ((d, d), (N, d, d)):
            raise ValueError(f"S must have shape {(d, d)} or {(N, d, d)}, got {Sn.shape}")
        Ss = 0.5 * (Sn + np.swapaxes(Sn, -1, -2))
        if not (np.all(np.isfinite(Sn)) and np.all(np.linalg.eigvalsh(Ss) > 0)):
            raise ValueError("S must be finite, symmetric positive definite")
    S = jnp.broadcast_to(jnp.asarray(S, dtype=float), (N, d, d))
    S = 0.5 * (S + jnp.swapaxes(S, -1, -2))
    delta = p_guess - centres
    q = jnp.einsum("ni,nij,nj->n", delta, S, delta)
    e1 = jnp.zeros(d).at[0].set(1.0)
    fallback = e1 / jnp.sqrt(S[:, 0, 0])[:, None]  # boundary point along the first axis
    ok = (q > 1e-24)[:, None]
    dr0 = jnp.where(ok, delta / jnp.sqrt(jnp.where(ok, q[:, None], 1.0)), fallback)
    r0 = centres + dr0
    E = jnp.einsum("ni,nij->nj", dr0, S)  # (r0 - o)^T S
    Fx = _embed(-2.0 * E, nx, idx)[:, None, :]
    fx = (-1.0 - jnp.sum(E * (r0 + centres), axis=-1))[:, None]
    return Fx, fx


def holding_radius_rows(p_guess, target_pos, r_hold, nx: int, pos_index=None):
    """Dynamic holding radius r_hold^2 <= |r - r_tar|^2 (paper 000 Eq. 9), linearised as Eq. 8.

    A spherical keep-out zone of radius r_hold about the target centre of mass, i.e.
    :func:`ellipsoid_keepout_rows` with S = I / r_hold^2, expanded about the point of the
    holding sphere on the segment from the target to the guessed chaser position.

    Args:
        p_guess: (N, d) guessed chaser positions [m].
        target_pos: (N, d) target centre-of-mass positions [m].
        r_hold: scalar or (N,) holding radius [m], > 0.
        nx: state dimension.
        pos_index: static tuple of the position columns.

    Returns:
        (Fx (N, 1, nx), fx (N, 1)): rows Fx x_{t+1} <= fx (row value equals the bound on the
        holding sphere, satisfied outside it).
    """
    _check("r_hold", r_hold, lo=0.0)
    p_guess = jnp.asarray(p_guess, dtype=float)
    N, d = p_guess.shape
    r = jnp.broadcast_to(jnp.asarray(r_hold, dtype=float), (N,))
    S = jnp.eye(d)[None] / (r * r)[:, None, None]
    return ellipsoid_keepout_rows(p_guess, target_pos, S, nx, pos_index)


def holding_radius_update(r_hold, pos_err, att_err, gamma, eta, zeta, r_min):
    """Next holding radius (paper 000 Sec. II.C.3; paper 002 Fig. 4 switching algorithm).

    r_hold(k+1) = max(gamma r_hold(k), r_min) if |pos_err| < eta and |att_err| < zeta,
    otherwise max(r_hold(k), r_min): the radius shrinks by gamma only when the chaser is near
    the holding position *and* pointing at the port, and never goes below r_min (distance
    between the two centres of mass in the docked position).

    Args:
        r_hold: current holding radius [m] (scalar), > 0.
        pos_err: chaser position error w.r.t. the holding point [m], scalar or vector
            (its Euclidean norm is used).
        att_err: attitude error [rad]: a scalar angle (wrapped to [-pi, pi) before taking the
            absolute value) or a rotation vector (its norm is used).
        gamma: shrink factor in (0, 1).
        eta: position tolerance [m], > 0.
        zeta: attitude tolerance [rad], > 0.
        r_min: lower limit r_hold,min [m], > 0.

    Returns:
        The next holding radius (scalar array).
    """
    _check("r_hold", r_hold, lo=0.0)
    _check("gamma", gamma, lo=0.0, hi=1.0)
    _check("eta", eta, lo=0.0)
    _check("zeta", zeta, lo=0.0)
    _check("r_min", r_min, lo=0.0)
    r_hold = jnp.asarray(r_hold, dtype=float)
    pos_err = jnp.asarray(pos_err, dtype=float)
    att_err = jnp.asarray(att_err, dtype=float)
    # squared norms: no sqrt, so gradients stay finite at zero error
    pos2 = jnp.sum(pos_err * pos_err)
    att = _wrap(att_err) if att_err.ndim == 0 else att_err
    att2 = jnp.sum(att * att)
    shrink = (pos2 < jnp.square(eta)) & (att2 < jnp.square(zeta))
    return jnp.maximum(jnp.where(shrink, gamma * r_hold, r_hold), r_min)


# --------------------------------------------------------------------------- cones


def entry_cone_rows(port_pos, axis_angle, half_angle, nx: int, pos_index=None):
    """Planar entry cone: two hyperplanes through the docking port (paper 000 Eq. 10;
    paper 001 Eqs. 5f-5g).

    With the port's outward axis (cos a, sin a) and half angle h, the normals are
    n_c1 = (sin(a + h), -cos(a + h)) and n_c2 = (sin(a - h), -cos(a - h)) and the rows are

        -n_c1 . r <= -n_c1 . r_dock,        n_c2 . r <= n_c2 . r_dock.

    Points r = r_dock + s (cos b, sin b) with s > 0 and |b - a| <= h (in front of the port,
    within the half angle) satisfy both rows; points behind the port or outside the wedge
    violate at least one. Rows have unit normals, so a row value is a distance [m].

    Args:
        port_pos: (N, 2) docking-port (cone apex) positions [m].
        axis_angle: (N,) outward port-axis angles [rad] (rotate with the target).
        half_angle: cone half angle [rad] in (0, pi/2).
        nx: state dimension.
        pos_index: static tuple of the two position columns.

    Returns:
        (Fx (N, 2, nx), fx (N, 2)).
    """
    _check("half_angle", half_angle, lo=0.0, hi=np.pi / 2)
    port_pos = jnp.asarray(port_pos, dtype=float)
    if port_pos.ndim != 2 or port_pos.shape[1] != 2:
        raise ValueError(f"port_pos must have shape (N, 2), got {port_pos.shape}")
    idx = _pos_index(pos_index, 2, nx)
    a = jnp.broadcast_to(jnp.asarray(axis_angle, dtype=float), port_pos.shape[:1])
    n1 = jnp.stack([jnp.sin(a + half_angle), -jnp.cos(a + half_angle)], axis=-1)
    n2 = jnp.stack([jnp.sin(a - half_angle), -jnp.cos(a - half_angle)], axis=-1)
    H = jnp.stack([-n1, n2], axis=1)  # (N, 2, 2)
    return _embed(H, nx, idx), jnp.einsum("nij,nj->ni", H, port_pos)


def _cone_faces_3d(axis, half_angle, n_faces: int, inscribed: bool):
    """Outward unit normals (N, n_faces, 3) of a polyhedral cone about unit ``axis``."""
    a = _safe_normalise(axis, jnp.array([1.0, 0.0, 0.0]))
    helper = jnp.where(
        (jnp.abs(a[:, :1]) < 0.9), jnp.array([1.0, 0.0, 0.0]), jnp.array([0.0, 1.0, 0.0])
    )
    e1 = _safe_normalise(jnp.cross(a, helper), helper)
    e2 = jnp.cross(a, e1)
    h = half_angle
    if inscribed:  # edges on the true cone: faces tangent to the cone of half angle h'
        h = jnp.arctan(jnp.tan(h) * np.cos(np.pi / n_faces))
    phi = 2 * np.pi * np.arange(n_faces) / n_faces
    m = np.cos(phi)[None, :, None] * e1[:, None] + np.sin(phi)[None, :, None] * e2[:, None]
    return jnp.cos(h) * m - jnp.sin(h) * a[:, None, :]


def approach_cone_rows_3d(
    port_pos, axis, half_angle, n_faces: int, nx: int, pos_index=None, inscribed=False
):
    """Polyhedral line-of-sight / approach cone in 3-D (paper 003 Eqs. 3.3, 3.12, 3.15).

    The LoS cone {r : angle(r - p, axis) <= half_angle} is approximated by the polyhedron
    P = {r : H (r - p) <= 0} with ``n_faces`` faces (paper 003 uses 4), each face tangent to
    the cone (``inscribed=False``: P contains the cone) or with its edges on the cone
    (``inscribed=True``: P is inside the cone). Rows: H r <= H p, unit outward normals.
    A rotating target (Eq. 3.15, H_{i+1} = H_i R^T) is handled by passing the rotated axis
    per stage (see :func:`target_frame`).

    Args:
        port_pos: (N, 3) cone apex (docking port) positions [m].
        axis: (N, 3) outward cone axes (need not be unit).
        half_angle: half angle [rad] in (0, pi/2).
        n_faces: number of faces (static int >= 3).
        nx: state dimension.
        pos_index: static tuple of the three position columns.
        inscribed: static bool, see above.

    Returns:
        (Fx (N, n_faces, nx), fx (N, n_faces)).
    """
    _check("half_angle", half_angle, lo=0.0, hi=np.pi / 2)
    if not isinstance(n_faces, (int, np.integer)) or n_faces < 3:
        raise ValueError(f"n_faces must be an int >= 3, got {n_faces!r}")
    port_pos = jnp.asarray(port_pos, dtype=float)
    if port_pos.ndim != 2 or port_pos.shape[1] != 3:
        raise ValueError(f"port_pos must have shape (N, 3), got {port_pos.shape}")
    idx = _pos_index(pos_index, 3, nx)
    axis = jnp.broadcast_to(jnp.asarray(axis, dtype=float), port_pos.shape)
    H = _cone_faces_3d(axis, half_angle, int(n_faces), bool(inscribed))
    return _embed(H, nx, idx), jnp.einsum("nij,nj->ni", H, port_pos)


def approach_cone_penalty_rows(
    port_pos,
    axis,
    half_angle,
    lam,
    nx: int,
    pos_index=None,
    n_faces: int = 4,
    terminal_only: bool = False,
    inscribed: bool = False,
):
    """Approach-cone penalty lambda 1^T (H x)_+ as soft rows (paper 003 Eqs. 3.3 and 3.8).

    The OCP's soft state rows cost rho^T max(0, Fx x - fx), so the external penalty
    lambda 1^T (H (x - p))_+ is *exactly* a set of cone rows with rho = lambda (DESIGN §2's
    slack formulation s >= H x, s >= 0, cost lambda 1^T s is what the solver does).

    Args:
        port_pos: (N, d) cone apex positions [m], d = 2 or 3.
        axis: d = 2: (N,) axis angles [rad]; d = 3: (N, 3) axis vectors.
        half_angle: half angle [rad] in (0, pi/2).
        lam: penalty weight lambda > 0 [cost per metre of violation].
        nx: state dimension.
        pos_index: static tuple of the position columns.
        n_faces: faces of the 3-D polyhedron (ignored for d = 2, which uses 2 rows).
        terminal_only: Eq. 3.3 (penalty on the last stage only) instead of Eq. 3.8 (all
            stages); implemented with the row mask.
        inscribed: 3-D polyhedron inside (True) or around (False) the cone.

    Returns:
        (Fx (N, m, nx), fx (N, m), rho (N, m) = lambda, mask (N, m)) -- a 4-tuple accepted
        by :func:`stack_rows`.
    """
    _check("lam", lam, lo=0.0)
    port_pos = jnp.asarray(port_pos, dtype=float)
    if port_pos.shape[-1] == 2:
        Fx, fx = entry_cone_rows(port_pos, axis, half_angle, nx, pos_index)
    else:
        Fx, fx = approach_cone_rows_3d(
            port_pos, axis, half_angle, n_faces, nx, pos_index, inscribed=inscribed
        )
    rho = jnp.broadcast_to(jnp.asarray(lam, dtype=float), fx.shape)
    mask = jnp.ones(fx.shape)
    if terminal_only:
        mask = mask.at[:-1].set(0.0)
    return Fx, fx, rho, mask


# --------------------------------------------------------------------------- rotating hyperplane


def rotating_hyperplane_rows(target_pos, normal_angle, offset, nx: int, pos_index=None):
    """Rotating-hyperplane keep-out zone (paper 001 Eq. 5e; paper 003 Eq. 3.5).

    With n = (cos phi, sin phi) the chaser must stay on the outer side of the line tangent to
    the keep-out circle (centre c, radius ``offset``) at c + offset n:
    n . (r - c) >= offset, returned as the row

        -n . r <= -offset - n . c.

    The whole half-space lies outside the circle (conservative). The normal angle phi rotates
    along the horizon, see :func:`hyperplane_angles`.

    Args:
        target_pos: (N, 2) keep-out centres [m].
        normal_angle: (N,) normal angles phi [rad].
        offset: keep-out radius r1 [m], > 0 (scalar or (N,)).
        nx: state dimension.
        pos_index: static tuple of the two position columns.

    Returns:
        (Fx (N, 1, nx), fx (N, 1)).
    """
    _check("offset", offset, lo=0.0)
    target_pos = jnp.asarray(target_pos, dtype=float)
    if target_pos.ndim != 2 or target_pos.shape[1] != 2:
        raise ValueError(f"target_pos must have shape (N, 2), got {target_pos.shape}")
    N = target_pos.shape[0]
    idx = _pos_index(pos_index, 2, nx)
    n = _unit2(jnp.broadcast_to(jnp.asarray(normal_angle, dtype=float), (N,)))
    off = jnp.broadcast_to(jnp.asarray(offset, dtype=float), (N,))
    Fx = _embed(-n, nx, idx)[:, None, :]
    fx = (-off - jnp.sum(n * target_pos, axis=-1))[:, None]
    return Fx, fx


def hyperplane_angles(theta0, theta_final, N: int, ts, rate_max, t0=0.0, direction: int = 0):
    """Normal angles of the rotating hyperplane along the horizon (paper 003 Eq. 3.6).

    The normal starts at ``theta0`` (the chaser's bearing from the keep-out centre when the
    rotation started, time 0) and rotates towards ``theta_final`` (the docking / approach-cone
    axis). Paper 003 splits the rotation into N equal steps over the horizon (rate
    |Delta| / (N ts)) and caps the rate at ``rate_max`` (the target's mean motion). With the
    current time ``t0`` (time since the rotation started) and stage t at time t0 + (t+1) ts:

        rate = min(rate_max, |Delta| / (t0 + N ts)),
        phi_t = theta0 + sign(Delta) min(|Delta|, rate (t0 + (t+1) ts)).

    So phi is monotone, moves at most rate_max ts per stage, and stops at theta_final
    (reached at the end of the horizon when the cap is inactive).

    Args:
        theta0: initial normal angle [rad].
        theta_final: final (docking-axis) angle [rad].
        N: number of stages (static int >= 1).
        ts: sampling time [s], > 0.
        rate_max: maximum rotation rate [rad/s], > 0.
        t0: current time since the rotation began [s], >= 0.
        direction: static; 0 = shortest way, +1 = anticlockwise, -1 = clockwise (paper 003
            prefers the direction of the natural relative orbit motion).

    Returns:
        (N,) normal angles [rad] (not wrapped; equal to theta_final modulo 2 pi at the end).
    """
    if not isinstance(N, (int, np.integer)) or N < 1:
        raise ValueError(f"N (horizon) must be an int >= 1, got {N!r}")
    if direction not in (-1, 0, 1):
        raise ValueError(f"direction must be -1, 0 or +1, got {direction!r}")
    _check("ts", ts, lo=0.0)
    _check("rate_max", rate_max, lo=0.0)
    _check("t0", t0, lo=0.0, lo_open=False)
    theta0 = jnp.asarray(theta0, dtype=float)
    raw = jnp.asarray(theta_final, dtype=float) - theta0
    if direction == 0:
        delta = _wrap(raw)
    elif direction == 1:
        delta = raw % (2 * jnp.pi)
    else:
        delta = -((-raw) % (2 * jnp.pi))
    mag = jnp.abs(delta)
    rate = jnp.minimum(rate_max, mag / (t0 + N * ts))
    times = t0 + ts * jnp.arange(1, N + 1, dtype=float)
    return theta0 + jnp.sign(delta) * jnp.minimum(mag, rate * times)


# --------------------------------------------------------------------------- other rows


def overshoot_row(n_hat, r2, nx: int, pos_index=None, target_pos=None):
    """Overshoot constraint n_hat^T (r - r_tar) >= r2 (paper 003 Eq. 3.9).

    The chaser may not come closer than r2 to the target along the (rotating) cone axis
    n_hat. Row: -n^T r <= -r2 - n^T r_tar, with n = n_hat / |n_hat|.

    Args:
        n_hat: (N, d) cone axes (normalised here).
        r2: minimum distance along the axis [m] (scalar or (N,)), >= 0.
        nx: state dimension.
        pos_index: static tuple of the position columns.
        target_pos: (N, d) target centre positions [m]; default the origin.

    Returns:
        (Fx (N, 1, nx), fx (N, 1)).
    """
    _check("r2", r2, lo=0.0, lo_open=False)
    n_hat = jnp.asarray(n_hat, dtype=float)
    N, d = n_hat.shape
    idx = _pos_index(pos_index, d, nx)
    n = _safe_normalise(n_hat, jnp.zeros(d).at[0].set(1.0))
    c = jnp.zeros((N, d)) if target_pos is None else jnp.asarray(target_pos, dtype=float)
    r2 = jnp.broadcast_to(jnp.asarray(r2, dtype=float), (N,))
    return _embed(-n, nx, idx)[:, None, :], (-r2 - jnp.sum(n * c, axis=-1))[:, None]


def velocity_bound_rows(v_max, N: int, nx: int, vel_index):
    """Docking velocity bound |v_i| <= v_max (paper 003 Eq. 3.13, |v|_inf <= v_max).

    Rows [E; -E] x_{t+1} <= [v_max; v_max] with E selecting the velocity columns.

    Args:
        v_max: scalar, (nv,) or (N, nv) bound [m/s], > 0.
        N: horizon length (static int >= 1).
        nx: state dimension.
        vel_index: static tuple of the nv velocity columns.

    Returns:
        (Fx (N, 2 nv, nx), fx (N, 2 nv)).
    """
    if not isinstance(N, (int, np.integer)) or N < 1:
        raise ValueError(f"N (horizon) must be an int >= 1, got {N!r}")
    _check("v_max", v_max, lo=0.0)
    idx = _check_index("vel_index", vel_index, nx)
    nv = len(idx)
    E = _embed(jnp.eye(nv), nx, idx)
    Fx = jnp.broadcast_to(jnp.concatenate([E, -E]), (N, 2 * nv, nx))
    v = jnp.broadcast_to(jnp.asarray(v_max, dtype=float), (N, nv))
    return Fx, jnp.concatenate([v, v], axis=1)


# --------------------------------------------------------------------------- target geometry


def target_angles(theta0, omega, N: int, ts, t0=0.0):
    """Attitude angles of a constantly rotating target at the stage instants t0 + (t+1) ts.

    Args:
        theta0: target angle at time 0 [rad].
        omega: body rate [rad/s].
        N: number of stages (static).
        ts: sampling time [s], > 0.
        t0: current time [s].

    Returns:
        (N,) angles [rad].
    """
    _check("ts", ts, lo=0.0)
    times = t0 + ts * jnp.arange(1, N + 1, dtype=float)
    return jnp.asarray(theta0, dtype=float) + jnp.asarray(omega, dtype=float) * times


def _rot2(angle):
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([jnp.stack([c, -s], -1), jnp.stack([s, c], -1)], -2)


def _rot3(angle, k):
    """Rotation matrices (N, 3, 3) by ``angle`` (N,) about unit axis k (3,) (Rodrigues)."""
    K = jnp.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    s, c = jnp.sin(angle)[:, None, None], jnp.cos(angle)[:, None, None]
    return jnp.eye(3) + s * K + (1 - c) * (K @ K)


def target_frame(port_body, target_pos, target_angle, axis_body=None, rot_axis=None):
    """Docking-port position and outward axis in the LVLH / inertial frame (paper 003
    Eq. 3.15; paper 000 Fig. 2).

    The port sits at ``port_body`` in the target body frame; the body is rotated by
    ``target_angle`` (about the plane normal for d = 2, about ``rot_axis`` for d = 3, default
    the x-axis as in paper 003 Sec. 3.4) and translated to ``target_pos``:
    p = r_tar + R(theta) port_body.

    Args:
        port_body: (d,) port position in the body frame [m].
        target_pos: (N, d) target centre-of-mass positions [m].
        target_angle: (N,) target attitude angles [rad].
        axis_body: outward port axis in the body frame: d = 2: angle [rad]; d = 3: (3,)
            vector. Default: the direction of ``port_body`` (port on a radial face).
        rot_axis: d = 3 only: (3,) rotation axis (normalised here); default (1, 0, 0).

    Returns:
        d = 2: (port_pos (N, 2), axis_angle (N,) [rad]);
        d = 3: (port_pos (N, 3), axis (N, 3) unit vectors).
    """
    port_body = jnp.asarray(port_body, dtype=float)
    target_pos = jnp.asarray(target_pos, dtype=float)
    N, d = target_pos.shape
    ang = jnp.broadcast_to(jnp.asarray(target_angle, dtype=float), (N,))
    if d == 2:
        R = _rot2(ang)
        port = target_pos + jnp.einsum("nij,j->ni", R, port_body)
        a_body = (
            jnp.arctan2(port_body[1], port_body[0])
            if axis_body is None
            else jnp.asarray(axis_body, dtype=float)
        )
        return port, ang + a_body
    if d != 3:
        raise ValueError(f"target_pos must have d = 2 or 3 columns, got {d}")
    k = jnp.array([1.0, 0.0, 0.0]) if rot_axis is None else jnp.asarray(rot_axis, dtype=float)
    k = k / jnp.linalg.norm(k)
    R = _rot3(ang, k)
    port = target_pos + jnp.einsum("nij,j->ni", R, port_body)
    a_body = port_body if axis_body is None else jnp.asarray(axis_body, dtype=float)
    a_body = a_body / jnp.linalg.norm(a_body)
    return port, jnp.einsum("nij,j->ni", R, a_body)


def hold_point(port_pos, axis_angle, r_hold, target_pos=None):
    """Holding position in front of the docking port (paper 000 Sec. II.C.3, Fig. 2).

    "The desired holding position is on the holding radius directly in front of the target's
    docking port": with ``target_pos`` given, the point of the holding circle/sphere
    |r - r_tar| = r_hold on the ray r = p + s e (s >= 0) from the port along its outward axis
    e (for a port on the axis through the centre of mass this is r_tar + r_hold e);
    without ``target_pos``, the holding distance is measured from the port: p + r_hold e.

    Args:
        port_pos: (N, d) port positions [m].
        axis_angle: d = 2: (N,) axis angles [rad]; or (N, d) axis vectors (any d).
        r_hold: scalar or (N,) holding radius [m], > 0.
        target_pos: optional (N, d) target centre positions [m].

    Returns:
        (N, d) holding positions [m]. If the ray misses the sphere (r_hold smaller than the
        port's offset from the axis) the closest point of the ray is used.
    """
    _check("r_hold", r_hold, lo=0.0)
    port_pos = jnp.asarray(port_pos, dtype=float)
    N, d = port_pos.shape
    axis_angle = jnp.asarray(axis_angle, dtype=float)
    if axis_angle.ndim == 2:
        e = _safe_normalise(axis_angle, jnp.zeros(d).at[0].set(1.0))
    else:
        e = _unit2(jnp.broadcast_to(axis_angle, (N,)))
    r = jnp.broadcast_to(jnp.asarray(r_hold, dtype=float), (N,))
    if target_pos is None:
        return port_pos + r[:, None] * e
    w = port_pos - jnp.asarray(target_pos, dtype=float)
    b = jnp.sum(e * w, axis=-1)
    disc = jnp.maximum(b * b - (jnp.sum(w * w, axis=-1) - r * r), 0.0)
    s = jnp.maximum(-b + jnp.sqrt(disc + 1e-300), 0.0)
    return port_pos + s[:, None] * e


# --------------------------------------------------------------------------- combining


def stack_rows(*row_sets, rho=1e6, pad_to: int | None = None):
    """Concatenate row sets along the row axis into fixed-size OCP arrays.

    Each row set is (F, f), (F, f, rho) or (F, f, rho, mask) with F (N, m_i, n), f (N, m_i);
    a set's rho / mask may be a scalar, (N,) (per stage) or (N, m_i). Missing rho defaults to
    the keyword ``rho`` (the OCP's default 1e6), missing masks to ones. ``pad_to`` appends
    inactive padding rows (F = 0, f = 1, mask = 0) up to a fixed total row count, so every
    MPC step can use the same OCP shapes.

    Returns:
        (F (N, m, n), f (N, m), rho (N, m), mask (N, m)) for OCP.Fx/fx/rho/x_mask (or
        Fu/fu/-/u_mask for input rows).
    """
    if not row_sets:
        raise ValueError("stack_rows needs at least one row set")
    Fs, fs, rhos, masks = [], [], [], []
    for k, rs in enumerate(row_sets):
        if len(rs) not in (2, 3, 4):
            raise ValueError(f"row set {k} must be (F, f[, rho[, mask]]), got {len(rs)} items")
        F, f = jnp.asarray(rs[0], dtype=float), jnp.asarray(rs[1], dtype=float)
        if F.ndim != 3 or f.shape != F.shape[:2]:
            raise ValueError(
                f"row set {k}: F must be (N, m, n) and f (N, m); got {F.shape}, {f.shape}"
            )
        r_k = jnp.asarray(rs[2] if len(rs) > 2 else rho, dtype=float)
        m_k = jnp.asarray(rs[3] if len(rs) > 3 else 1.0, dtype=float)
        if r_k.ndim == 1:
            r_k = r_k[:, None]
        if m_k.ndim == 1:
            m_k = m_k[:, None]
        Fs.append(F)
        fs.append(f)
        rhos.append(jnp.broadcast_to(r_k, f.shape))
        masks.append(jnp.broadcast_to(m_k, f.shape))
    F, f = jnp.concatenate(Fs, axis=1), jnp.concatenate(fs, axis=1)
    R, M = jnp.concatenate(rhos, axis=1), jnp.concatenate(masks, axis=1)
    if pad_to is not None:
        N, m, n = F.shape
        if pad_to < m:
            raise ValueError(f"pad_to must be >= the number of rows ({m}), got {pad_to}")
        p = pad_to - m
        F = jnp.concatenate([F, jnp.zeros((N, p, n))], axis=1)
        f = jnp.concatenate([f, jnp.ones((N, p))], axis=1)
        R = jnp.concatenate([R, jnp.broadcast_to(jnp.asarray(rho, dtype=float), (N, p))], 1)
        M = jnp.concatenate([M, jnp.zeros((N, p))], axis=1)
    return F, f, R, M
