"""The papers' constraints as blocks: thrust boxes, keep-out ellipsoids and spheres, the
holding radius, entry and approach cones, planes and hyperplanes, overshoot, speed bounds, L1
cost rows, and rows planned between samples (the package docstring)."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from rvdjax.constraints.blocks import (
    Block,
    _block,
    _check,
    _check_index,
    _concrete,
    _embed,
    _pos_index,
    _safe_normalise,
    _unit2,
    _wrap,
)

__all__ = [
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


# --------------------------------------------------------------------------- input rows


def thrust_box(u_max, N: int, nu: int | None = None, name: str = "thrust") -> Block:
    """Thrust / torque box |u_i| <= u_max on every stage (paper 000 Eq. 5): hard input rows
    ``[I; -I] u_t <= [u_max; u_max]``.

    Args:
        u_max: scalar or (nu,) bounds [N or N m; m/s for delta-v inputs], > 0.
        N: horizon length (static int >= 1).
        nu: number of inputs; required when ``u_max`` is a scalar.
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
    eye = jnp.eye(nu, dtype=u_max.dtype)
    Fu = jnp.broadcast_to(jnp.concatenate([eye, -eye]), (N, 2 * nu, nu))
    fu = jnp.broadcast_to(jnp.concatenate([u_max, u_max]), (N, 2 * nu))
    return _block(Fu, fu, name, acts_on="u")


# --------------------------------------------------------------------------- keep-out rows


def ellipsoid_keep_out(
    p_guess, centres, S, nx: int, pos_index=None, rho=1e6, name="keep_out", kind="hard"
) -> Block:
    """Linearised ellipsoidal keep-out zone (paper 000 Eqs. 6-8 and 12-13).

    Keep-out set: (r - o)^T S (r - o) < 1 (S symmetric positive definite [1/m^2]). The
    expansion point is the boundary point on the segment from the centre o to the guessed
    position p (previous plan): r0 = o + (p - o) / sqrt((p - o)^T S (p - o)) — the paper's
    correction: r0, not r_obj. Eq. 8 expanded about r0 is the tangent half-space
    n^T (r - r0) >= 0 with n = S (r0 - o), returned with a unit normal:

        -n_hat^T r <= -n_hat^T r0.

    The row is tangent to the ellipsoid at r0 and, since the quadratic is convex, its feasible
    half-space lies entirely outside the keep-out zone. Linearised about the point itself
    (p = r) the slack of a sphere is |r - o| - radius. If p == o the expansion direction falls
    back to the first position axis.

    Args:
        p_guess: (N, d) guessed chaser positions at stages t (for x_{t+1}) [m].
        centres: (N, d) or (N, k, d) zone centres at the same instants [m] (k zones).
        S: (d, d), (N, d, d) (one zone per stage) or (N, k, d, d) shape matrices [1/m^2]; a
            sphere of radius R has S = I / R^2 (:func:`sphere_keep_out`).
        nx: state dimension.
        pos_index: static tuple of the d position columns of the state (default first d).
        rho: penalty per metre of violation (scalar or per row).

    Returns:
        A state :class:`Block` with one row per zone (N, k, nx).
    """
    p_guess = jnp.asarray(p_guess, dtype=float)
    centres = jnp.asarray(centres, dtype=float)
    N, d = p_guess.shape
    idx = _pos_index(pos_index, d, nx)
    single = centres.ndim == 2
    if single:
        centres = centres[:, None, :]
    k = centres.shape[1]
    if _concrete(S):
        Sn = np.asarray(S, dtype=float)
        Ss = 0.5 * (Sn + np.swapaxes(Sn, -1, -2))
        if not (np.all(np.isfinite(Sn)) and np.all(np.linalg.eigvalsh(Ss) > 0)):
            raise ValueError("S must be finite, symmetric positive definite")
    S = jnp.asarray(S, dtype=float)
    if S.ndim == 3:  # (N, d, d): one zone, per stage
        S = S[:, None]
    S = jnp.broadcast_to(S, (N, k, d, d))
    S = 0.5 * (S + jnp.swapaxes(S, -1, -2))
    delta = p_guess[:, None, :] - centres  # (N, k, d)
    q = jnp.einsum("nki,nkij,nkj->nk", delta, S, delta)
    e1 = jnp.zeros(d).at[0].set(1.0)
    fallback = e1 / jnp.sqrt(S[..., 0, 0])[..., None]  # boundary point along the first axis
    ok = (q > 1e-24)[..., None]
    dr0 = jnp.where(ok, delta / jnp.sqrt(jnp.where(ok, q[..., None], 1.0)), fallback)
    r0 = centres + dr0
    n = jnp.einsum("nkij,nkj->nki", S, dr0)  # S (r0 - o), outward normal at r0
    n_hat = n / jnp.linalg.norm(n, axis=-1, keepdims=True)
    F = _embed(-n_hat, nx, idx)
    f = -jnp.sum(n_hat * r0, axis=-1)
    return _block(F, f, name, kind=kind, rho=rho)


def sphere_keep_out(
    p_guess, centres, radius, nx: int, pos_index=None, rho=1e6, name="keep_out", kind="hard"
) -> Block:
    """Spherical (circular) keep-out zones, :func:`ellipsoid_keep_out` with S = I / r^2.

    Args:
        p_guess: (N, d) guessed positions [m].
        centres: (N, d) or (N, k, d) centres [m].
        radius: scalar, (k,) per zone, (N,) per stage (one zone) or (N, k) [m], > 0.
    """
    _check("radius", radius, lo=0.0)
    p_guess = jnp.asarray(p_guess, dtype=float)
    centres = jnp.asarray(centres, dtype=float)
    N, d = p_guess.shape
    k = 1 if centres.ndim == 2 else centres.shape[1]
    r = jnp.asarray(radius, dtype=float)
    if r.ndim == 1 and centres.ndim == 2:
        r = r[:, None]  # per stage, one zone
    r = jnp.broadcast_to(r, (N, k))
    S = jnp.eye(d)[None, None] / (r * r)[..., None, None]
    return ellipsoid_keep_out(p_guess, centres, S, nx, pos_index, rho, name, kind)


def holding_radius(
    p_guess, target_pos, r_hold, nx: int, pos_index=None, rho=1e6, name="holding_radius"
) -> Block:
    """Dynamic holding radius r_hold <= |r - r_tar| (paper 000 Eq. 9), linearised as Eq. 8:
    a spherical keep-out zone of radius r_hold about the target's centre of mass.

    Args:
        p_guess: (N, d) guessed chaser positions [m].
        target_pos: (N, d) target centre-of-mass positions [m].
        r_hold: scalar or (N,) holding radius [m], > 0.
    """
    return sphere_keep_out(p_guess, target_pos, r_hold, nx, pos_index, rho, name)


def holding_radius_update(r_hold, pos_err, att_err, gamma, eta, zeta, r_min, gate=True):
    """Next holding radius (paper 000 Sec. II.C.3; paper 002 Fig. 4 switching algorithm).

    r_hold(k+1) = max(gamma r_hold(k), r_min) if |pos_err| < eta and |att_err| < zeta (and the
    optional traced ``gate``, e.g. "in the final phase"), otherwise r_hold(k): the radius
    shrinks by gamma only when the chaser is near the holding position *and* pointing at the
    port, and never below r_min (distance between the centres of mass when docked).

    Args:
        r_hold: current holding radius [m] (scalar), > 0.
        pos_err: position error w.r.t. the holding point [m]: its Euclidean norm, or a vector.
        att_err: attitude error [rad]: a scalar angle (wrapped to [-pi, pi)) or a rotation
            vector (its norm is used).
        gamma: shrink factor in (0, 1); eta: position tolerance [m]; zeta: attitude tolerance
            [rad]; r_min: lower limit r_hold,min [m].

    Returns:
        (next holding radius, shrink condition met).
    """
    _check("r_hold", r_hold, lo=0.0)
    _check("gamma", gamma, lo=0.0, hi=1.0)
    _check("eta", eta, lo=0.0)
    _check("zeta", zeta, lo=0.0)
    _check("r_min", r_min, lo=0.0)
    r_hold = jnp.asarray(r_hold, dtype=float)
    pos_err = jnp.asarray(pos_err, dtype=float)
    att_err = jnp.asarray(att_err, dtype=float)
    pos = jnp.abs(pos_err) if pos_err.ndim == 0 else jnp.linalg.norm(pos_err)
    att = jnp.abs(_wrap(att_err)) if att_err.ndim == 0 else jnp.linalg.norm(att_err)
    close = (pos < eta) & (att < zeta)
    shrink = close & gate
    return jnp.where(shrink, jnp.maximum(gamma * r_hold, r_min), r_hold), close


# --------------------------------------------------------------------------- cones


def entry_cone(
    port_pos,
    axis_angle,
    half_angle,
    nx: int,
    pos_index=None,
    rho=1e6,
    name="entry_cone",
    kind="hard",
) -> Block:
    """Planar entry cone: two hyperplanes through the docking port (paper 000 Eq. 10;
    paper 001 Eqs. 5f-5g; paper 002 Eqs. 5-6).

    With the port's outward axis (cos a, sin a) and half angle h, the normals are
    n_c1 = (sin(a + h), -cos(a + h)) and n_c2 = (sin(a - h), -cos(a - h)) and the rows are

        -n_c1 . r <= -n_c1 . r_dock,        n_c2 . r <= n_c2 . r_dock.

    Points r = r_dock + s (cos b, sin b) with s > 0 and |b - a| <= h (in front of the port,
    within the half angle) satisfy both rows; points behind the port or outside the wedge
    violate at least one.

    Args:
        port_pos: (N, 2) docking-port (cone apex) positions [m].
        axis_angle: (N,) outward port-axis angles [rad] (rotate with the target).
        half_angle: cone half angle [rad] in (0, pi/2).
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
    return _block(_embed(H, nx, idx), jnp.einsum("nij,nj->ni", H, port_pos), name, kind, rho=rho)


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


def approach_cone(
    port_pos,
    axis,
    half_angle,
    n_faces: int,
    nx: int,
    pos_index=None,
    inscribed=False,
    rho=1e6,
    name="approach_cone",
    kind="hard",
) -> Block:
    """Polyhedral line-of-sight / approach cone in 3-D (paper 003 Eqs. 3.3, 3.12, 3.15).

    The LoS cone {r : angle(r - p, axis) <= half_angle} is approximated by the polyhedron
    P = {r : H (r - p) <= 0} with ``n_faces`` faces (paper 003 uses 4), each face tangent to
    the cone (``inscribed=False``: P contains the cone) or with its edges on the cone
    (``inscribed=True``: P is inside the cone). Rows: H r <= H p, unit outward normals. A
    rotating target (Eq. 3.15, H_{i+1} = H_i R^T) is handled by passing the rotated axis per
    stage.

    Args:
        port_pos: (N, 3) cone apex (docking port) positions [m].
        axis: (N, 3) outward cone axes (need not be unit).
        half_angle: half angle [rad] in (0, pi/2).
        n_faces: number of faces (static int >= 3).
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
    return _block(_embed(H, nx, idx), jnp.einsum("nij,nj->ni", H, port_pos), name, kind, rho=rho)


def approach_cone_penalty(
    port_pos,
    axis,
    half_angle,
    lam,
    nx: int,
    pos_index=None,
    n_faces: int = 4,
    terminal_only: bool = False,
    inscribed: bool = False,
    name="approach_cone",
) -> Block:
    """Approach-cone penalty lambda 1^T (H x)_+ (paper 003 Eqs. 3.3 and 3.8) as a "penalty"
    block: the OCP's soft rows cost rho^T max(0, F x - f), so the external penalty
    lambda 1^T (H (x - p))_+ is *exactly* the cone rows with rho = lambda (DESIGN §2's slack
    formulation s >= H x, s >= 0, cost lambda 1^T s is what the solver does).

    Args:
        port_pos: (N, d) cone apex positions [m], d = 2 or 3.
        axis: d = 2: (N,) axis angles [rad]; d = 3: (N, 3) axis vectors.
        lam: penalty weight lambda > 0 [cost per metre outside the cone].
        n_faces: faces of the 3-D polyhedron (d = 2 uses 2 rows).
        terminal_only: Eq. 3.3 (penalty on the last stage only) instead of Eq. 3.8.
    """
    _check("lam", lam, lo=0.0)
    port_pos = jnp.asarray(port_pos, dtype=float)
    if port_pos.shape[-1] == 2:
        b = entry_cone(port_pos, axis, half_angle, nx, pos_index, rho=lam, name=name)
    else:
        b = approach_cone(
            port_pos, axis, half_angle, n_faces, nx, pos_index, inscribed, rho=lam, name=name
        )
    b = b.with_(kind="penalty")
    if terminal_only:
        b = b.masked(jnp.zeros(b.N).at[-1].set(1.0))
    return b


# --------------------------------------------------------------------------- planes


def keep_out_plane(
    normals,
    offset,
    nx: int,
    pos_index=None,
    centre=None,
    rho=1e6,
    name="keep_out",
    kind="hard",
) -> Block:
    """Keep-out half-space n . (r - c) >= offset per stage (paper 001 Eq. 5e; paper 003
    Eqs. 3.5-3.6): the plane tangent to the keep-out sphere (circle) of radius ``offset`` about
    ``c`` at c + offset n. The whole half-space lies outside the zone (conservative). Row:
    -n . r <= -offset - n . c.

    Args:
        normals: (N, d) unit normals (rotating along the horizon).
        offset: keep-out radius [m], >= 0 (scalar or (N,)).
        centre: (N, d) or (d,) zone centres [m]; default the origin.
    """
    _check("offset", offset, lo=0.0, lo_open=False)
    n = jnp.asarray(normals, dtype=float)
    N, d = n.shape
    idx = _pos_index(pos_index, d, nx)
    c = (
        jnp.zeros((N, d))
        if centre is None
        else jnp.broadcast_to(jnp.asarray(centre, float), (N, d))
    )
    off = jnp.broadcast_to(jnp.asarray(offset, dtype=float), (N,))
    F = _embed(-n, nx, idx)[:, None, :]
    f = (-off - jnp.sum(n * c, axis=-1))[:, None]
    return _block(F, f, name, kind, rho=rho)


def rotating_hyperplane(
    target_pos, normal_angle, offset, nx: int, pos_index=None, rho=1e6, name="keep_out_plane"
) -> Block:
    """Planar rotating-hyperplane keep-out zone (paper 001 Eq. 5e): :func:`keep_out_plane`
    with the normal n = (cos phi, sin phi) given by its angle per stage.

    Args:
        target_pos: (N, 2) keep-out centres [m].
        normal_angle: (N,) normal angles phi [rad].
        offset: keep-out radius [m], > 0.
    """
    _check("offset", offset, lo=0.0)
    target_pos = jnp.asarray(target_pos, dtype=float)
    if target_pos.ndim != 2 or target_pos.shape[1] != 2:
        raise ValueError(f"target_pos must have shape (N, 2), got {target_pos.shape}")
    n = _unit2(jnp.broadcast_to(jnp.asarray(normal_angle, dtype=float), target_pos.shape[:1]))
    return keep_out_plane(n, offset, nx, pos_index, target_pos, rho, name)


def overshoot(n_hat, r2, nx: int, pos_index=None, target_pos=None, rho=1e6, name="overshoot"):
    """Overshoot constraint n_hat^T (r - r_tar) >= r2 (paper 003 Eq. 3.9): the chaser may not
    come closer than r2 to the target along the (rotating) cone axis n_hat.

    Args:
        n_hat: (N, d) cone axes (normalised here).
        r2: minimum distance along the axis [m] (scalar or (N,)), >= 0.
        target_pos: (N, d) target centre positions [m]; default the origin.
    """
    _check("r2", r2, lo=0.0, lo_open=False)
    n_hat = jnp.asarray(n_hat, dtype=float)
    d = n_hat.shape[-1]
    n = _safe_normalise(n_hat, jnp.zeros(d).at[0].set(1.0))
    return keep_out_plane(n, r2, nx, pos_index, target_pos, rho, name)


def velocity_bound(v_max, N: int, nx: int, vel_index, rho=1e6, name="speed") -> Block:
    """Docking velocity bound |v_i| <= v_max (paper 003 Eq. 3.13, |v|_inf <= v_max): rows
    [E; -E] x_{t+1} <= [v_max; v_max] with E selecting the velocity columns.

    Args:
        v_max: scalar, (nv,) or (N, nv) bound [m/s], > 0.
        N: horizon length (static int >= 1).
        vel_index: static tuple of the nv velocity columns.
    """
    if not isinstance(N, (int, np.integer)) or N < 1:
        raise ValueError(f"N (horizon) must be an int >= 1, got {N!r}")
    _check("v_max", v_max, lo=0.0)
    idx = _check_index("vel_index", vel_index, nx)
    nv = len(idx)
    E = _embed(jnp.eye(nv), nx, idx)
    F = jnp.broadcast_to(jnp.concatenate([E, -E]), (N, 2 * nv, nx))
    v = jnp.broadcast_to(jnp.asarray(v_max, dtype=float), (N, nv))
    return _block(F, jnp.concatenate([v, v], axis=1), name, rho=rho)


def cost_rows(W, centre_value, rho=1.0, name="l1_cost") -> Block:
    """Exact L1 cost terms ||W (x - x_s)||_1 as "penalty" rows (paper 003 Eq. 2.10): each row
    w_j gives the pair +-w_j (x - x_s) <= 0 with penalty 1, and max(0, g) + max(0, -g) = |g|.

    Args:
        W: (N, k, nx) weight rows per stage.
        centre_value: (N, k) the values W x_s.
    """
    W = jnp.asarray(W, dtype=float)
    Wr = jnp.asarray(centre_value, dtype=float)
    return _block(
        jnp.concatenate([W, -W], axis=1),
        jnp.concatenate([Wr, -Wr], axis=1),
        name,
        "penalty",
        rho=rho,
    )


def between_samples(block: Block, back, name: str | None = None) -> Block:
    """A state block's rows also at instants between samples where the state is a linear
    function of the sample it precedes: x(tau_j) = back_j x_{t+1} (a coast after an
    impulsive delta-v: back_j = e^{-Ac (Ts - tau_j)}; also after a finite burn has ended).

    Args:
        block: state rows ``F x_{t+1} <= f`` (N, m, nx).
        back: (M, nx, nx) or per stage (N, M, nx, nx) maps from x_{t+1} to the M instants.

    Returns:
        A block of M m rows per stage, ``(F back_j) x_{t+1} <= f``, instant-major; its slack is
        the original row's slack at x(tau_j).
    """
    if block.acts_on != "x":
        raise ValueError("between_samples takes a state block")
    back = jnp.asarray(back)
    M = back.shape[-3]
    if back.ndim == 3:  # one set of maps for every stage
        back = back[None]
    # products and a sum, not a matrix product: one fused kernel on a GPU and on a CPU (a
    # product over the maps broadcast to every stage made XLA's CPU compiler write 1.9 MB of
    # copies for a chunk of 32 thesis-vbar slots first)
    F = jnp.sum(block.F[:, None, :, :, None] * back[:, :, None], axis=-2)
    F = F.reshape(block.N, M * block.m, -1)
    tile = lambda a: jnp.tile(a, (1, M))  # noqa: E731
    return dataclasses.replace(
        block,
        F=F,
        f=tile(block.f),
        rho=tile(block.rho),
        mask=tile(block.mask),
        hard=None if block.hard is None else tile(block.hard),
        name=block.name if name is None else name,
    )
