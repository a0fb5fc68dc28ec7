"""Geometric tests of the constraint library (rvdjax.constraints): named blocks of rows."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rvdjax  # noqa: F401  (float64)
from rvdjax import constraints as C

RNG = np.random.default_rng(0)
NX = 6  # planar 3-DOF state (x, y, theta, vx, vy, omega)
POS = (0, 1)


def _state(p, nx=NX, pos=POS):
    x = np.zeros(nx)
    x[list(pos)] = p
    return x


def _rowval(block, p, t=0, nx=NX, pos=POS):
    """Row values F x - f at position p (positive = violated)."""
    return np.asarray(block.F[t]) @ _state(p, nx, pos) - np.asarray(block.f[t])


def test_thrust_box():
    b = C.thrust_box(np.array([1.0, 2.0, 0.5]), N=3)
    assert b.F.shape == (3, 6, 3) and b.f.shape == (3, 6)
    assert b.acts_on == "u" and b.kind == "hard" and b.name == "thrust"
    u_in, u_out = np.array([0.9, -1.9, 0.4]), np.array([0.0, 2.1, 0.0])
    assert np.all(np.asarray(b.F[1]) @ u_in <= b.f[1])
    assert np.any(np.asarray(b.F[1]) @ u_out > b.f[1])
    assert C.thrust_box(0.3, N=2, nu=2).F.shape == (2, 4, 2)


@pytest.mark.parametrize("three_d", [False, True])
def test_ellipsoid_keepout_tangent_and_conservative(three_d):
    d = 3 if three_d else 2
    nx, pos = (6, (0, 1, 2)) if three_d else (NX, POS)
    N = 4
    L = RNG.normal(size=(d, d))
    S = L @ L.T + 0.5 * np.eye(d)
    centres = RNG.normal(size=(N, d))
    guess = centres + 3.0 * RNG.normal(size=(N, d))
    b = C.ellipsoid_keep_out(guess, centres, S, nx, pos)
    assert b.F.shape == (N, 1, nx) and b.f.shape == (N, 1)
    np.testing.assert_allclose(np.linalg.norm(b.F, axis=-1), 1.0, rtol=1e-12)  # unit normals
    for t in range(N):
        dl = guess[t] - centres[t]
        r0 = centres[t] + dl / np.sqrt(dl @ S @ dl)
        assert abs(_rowval(b, r0, t, nx, pos)[0]) < 1e-9  # tangent at r0
        assert _rowval(b, guess[t], t, nx, pos)[0] < 0  # guess outside is accepted
        # points inside the ellipsoid violate the row
        z = RNG.normal(size=(200, d))
        z *= (RNG.uniform(size=(200, 1)) ** (1 / d)) / np.linalg.norm(z, axis=1, keepdims=True)
        inside = centres[t] + z @ np.linalg.inv(np.linalg.cholesky(S)) * 0.999
        assert np.all(np.einsum("ki,ij,kj->k", inside - centres[t], S, inside - centres[t]) < 1)
        assert all(_rowval(b, p, t, nx, pos)[0] > 0 for p in inside)
        # every feasible point of the half-space lies outside the ellipsoid
        pts = centres[t] + 5.0 * RNG.uniform(-1, 1, size=(2000, d))
        ok = np.array([_rowval(b, p, t, nx, pos)[0] <= 0 for p in pts])
        q = np.einsum("ki,ij,kj->k", pts - centres[t], S, pts - centres[t])
        assert ok.any() and np.all(q[ok] >= 1 - 1e-9)


def test_sphere_margin_is_the_distance():
    """A sphere linearised at the point itself: the slack is |r - o| - radius (metres)."""
    o = RNG.normal(size=(5, 3)) * 10
    r = o + RNG.normal(size=(5, 3)) * 30
    radii = np.abs(RNG.normal(size=5)) * 20 + 1
    for k in range(5):
        b = C.sphere_keep_out(r[k][None], o[k][None], radii[k], 6)
        m = C.block_margin(b, np.concatenate([r[k], np.zeros(3)]))
        assert float(m[0, 0]) == pytest.approx(np.linalg.norm(r[k] - o[k]) - radii[k], abs=1e-9)


def test_ellipsoid_degenerate_guess_finite():
    b = C.ellipsoid_keep_out(np.zeros((2, 2)), np.zeros((2, 2)), np.eye(2), NX)
    assert np.all(np.isfinite(b.F)) and np.all(np.isfinite(b.f))


def test_holding_radius_rows():
    N = 3
    tgt = RNG.normal(size=(N, 2))
    guess = tgt + np.array([[2.0, 1.0], [0.0, -3.0], [-1.0, 0.5]])
    r = np.array([1.0, 1.5, 0.8])
    b = C.holding_radius(guess, tgt, r, NX, POS)
    assert b.name == "holding_radius"
    for t in range(N):
        u = (guess[t] - tgt[t]) / np.linalg.norm(guess[t] - tgt[t])
        assert abs(_rowval(b, tgt[t] + r[t] * u, t)[0]) < 1e-9
        assert _rowval(b, tgt[t] + 0.9 * r[t] * u, t)[0] > 0
        assert _rowval(b, tgt[t], t)[0] > 0
    with pytest.raises(ValueError, match="radius"):
        C.holding_radius(guess, tgt, -1.0, NX)


def test_holding_radius_update_rule():
    kw = dict(gamma=0.9, eta=0.1, zeta=0.2, r_min=0.5)

    def upd(r, pe, ae, gate=True):
        return float(C.holding_radius_update(r, pe, ae, **kw, gate=gate)[0])

    assert upd(1.0, [0.05, 0.0], 0.1) == pytest.approx(0.9)  # both conditions: shrink
    assert upd(1.0, [0.2, 0.0], 0.1) == pytest.approx(1.0)  # position error too large
    assert upd(1.0, [0.05, 0.0], 0.3) == pytest.approx(1.0)  # attitude error too large
    assert upd(1.0, [0.05, 0.0], 2 * np.pi + 0.1) == pytest.approx(0.9)  # angle wrapped
    assert upd(1.0, [0.05, 0.0], 0.1, gate=False) == pytest.approx(1.0)  # gated off
    assert upd(0.52, [0.0, 0.0], 0.0) == pytest.approx(0.5)  # floored at r_min
    _, close = C.holding_radius_update(1.0, 0.05, 0.1, **kw, gate=False)
    assert bool(close)  # the condition is reported even when gated
    r = 1.0
    for _ in range(50):
        r = upd(r, [0.0, 0.0], 0.0)
    assert r == pytest.approx(0.5)
    for bad, name in [({"gamma": 1.0}, "gamma"), ({"eta": 0.0}, "eta"), ({"r_min": -1}, "r_min")]:
        with pytest.raises(ValueError, match=name):
            C.holding_radius_update(1.0, 0.0, 0.0, **{**kw, **bad})


@pytest.mark.parametrize("a", [0.0, 0.7, np.pi / 2, 2.5, -2.0])
def test_entry_cone_accepts_inside_rejects_outside(a):
    N, h = 2, np.deg2rad(20)
    port = np.array([[0.3, -0.2], [1.0, 2.0]])
    b = C.entry_cone(port, np.full(N, a), h, NX, POS)
    assert b.F.shape == (N, 2, NX)
    for t in range(N):
        for beta in np.linspace(-0.95 * h, 0.95 * h, 7):
            for s in (0.01, 1.0, 10.0):
                p = port[t] + s * np.array([np.cos(a + beta), np.sin(a + beta)])
                assert np.all(_rowval(b, p, t) <= 1e-12)
        for beta in (1.1 * h, -1.1 * h, np.pi / 2, np.pi, np.pi - 0.5 * h):
            p = port[t] + 1.0 * np.array([np.cos(a + beta), np.sin(a + beta)])
            assert np.any(_rowval(b, p, t) > 0)
        assert np.allclose(_rowval(b, port[t], t), 0.0)  # apex on both planes


@pytest.mark.parametrize("inscribed", [False, True])
def test_approach_cone_3d(inscribed):
    N, h, k = 2, np.deg2rad(30), 4
    port = RNG.normal(size=(N, 3))
    axis = RNG.normal(size=(N, 3))
    pos = (0, 1, 2)
    b = C.approach_cone(port, axis, h, k, 6, pos, inscribed=inscribed)
    assert b.F.shape == (N, k, 6)
    for t in range(N):
        a = axis[t] / np.linalg.norm(axis[t])
        v = RNG.normal(size=(400, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        ang = np.arccos(np.clip(v @ a, -1, 1))
        feas = np.array([np.all(_rowval(b, port[t] + 2 * vi, t, 6, pos) <= 1e-12) for vi in v])
        if inscribed:  # polyhedron inside the cone
            assert np.all(ang[feas] <= h + 1e-9)
        else:  # cone inside the polyhedron
            assert np.all(feas[ang <= h])
        assert not np.any(feas[ang > np.pi / 2])  # nothing behind the port
        assert np.all(_rowval(b, port[t] + a, t, 6, pos) < 0)  # axis strictly inside


def test_approach_cone_penalty():
    port, ang = np.zeros((3, 2)), np.array([0.0, 0.1, 0.2])
    b = C.approach_cone_penalty(port, ang, 0.3, 7.0, NX, POS, terminal_only=True)
    assert b.kind == "penalty" and np.all(b.rho == 7.0) and b.F.shape == (3, 2, NX)
    assert np.array_equal(np.asarray(b.mask), [[0, 0], [0, 0], [1, 1]])
    e = C.entry_cone(port, ang, 0.3, NX, POS)
    assert np.allclose(b.F, e.F) and np.allclose(b.f, e.f)
    with pytest.raises(ValueError, match="lam"):
        C.approach_cone_penalty(port, ang, 0.3, 0.0, NX)


def test_rotating_hyperplane_rows():
    N = 3
    c = RNG.normal(size=(N, 2))
    phi = np.array([0.3, 1.5, -2.0])
    b = C.rotating_hyperplane(c, phi, 1.2, NX, POS)
    for t in range(N):
        n = np.array([np.cos(phi[t]), np.sin(phi[t])])
        assert abs(_rowval(b, c[t] + 1.2 * n, t)[0]) < 1e-12  # tangent point
        assert _rowval(b, c[t] + 2.0 * n, t)[0] < 0
        assert _rowval(b, c[t], t)[0] > 0
        z = RNG.uniform(-1, 1, size=(300, 2)) * 1.2
        z = z[np.linalg.norm(z, axis=1) < 1.2]
        assert all(_rowval(b, c[t] + zi, t)[0] > 0 for zi in z)  # circle excluded


def test_overshoot_and_velocity_rows():
    n = np.array([[0.0, 2.0], [1.0, 1.0]])
    tgt = np.array([[1.0, 1.0], [0.0, 0.0]])
    b = C.overshoot(n, 0.5, NX, POS, target_pos=tgt)
    assert _rowval(b, [1.0, 1.6], 0)[0] < 0 and _rowval(b, [5.0, 1.4], 0)[0] > 0
    assert abs(_rowval(b, 0.5 * np.array([1, 1]) / np.sqrt(2), 1)[0]) < 1e-12
    v = C.velocity_bound(0.1, 2, NX, (3, 4, 5))
    assert v.F.shape == (2, 6, NX) and v.name == "speed"
    x_ok, x_bad = np.array([9, 9, 9, 0.05, -0.09, 0.0]), np.array([0, 0, 0, 0, -0.11, 0])
    assert np.all(np.asarray(v.F[0]) @ x_ok <= v.f[0])
    assert np.any(np.asarray(v.F[1]) @ x_bad > v.f[1])
    with pytest.raises(ValueError, match="v_max"):
        C.velocity_bound(-0.1, 2, NX, (3, 4))
    with pytest.raises(ValueError, match="vel_index"):
        C.velocity_bound(0.1, 2, NX, (3, 9))


def test_cost_rows_are_exact_l1():
    """Cost rows: rho max(0, g) + rho max(0, -g) = |W (x - x_s)| for each row of W."""
    W = RNG.normal(size=(2, 3, NX))
    xs = RNG.normal(size=(2, NX))
    b = C.cost_rows(W, np.einsum("tij,tj->ti", W, xs))
    assert b.kind == "penalty" and b.F.shape == (2, 6, NX)
    x = RNG.normal(size=NX)
    g = np.einsum("tij,j->ti", np.asarray(b.F), x) - np.asarray(b.f)
    l1 = np.abs(np.einsum("tij,tj->ti", W, x[None] - xs))
    np.testing.assert_allclose(np.maximum(g, 0).reshape(2, 2, 3).sum(1), l1, rtol=1e-12)


def test_stack_hard_mask_and_margins():
    N = 2
    a = C.entry_cone(np.zeros((N, 2)), np.zeros(N), 0.3, NX, rho=1e4)
    b = C.approach_cone_penalty(np.zeros((N, 2)), np.zeros(N), 0.3, 5.0, NX, terminal_only=True)
    c = C.velocity_bound(0.1, N, NX, (3, 4)).masked(np.array([0.0, 1.0]))
    F, f, rho, mask = C.stack([a, b, c])
    assert F.shape == (N, 8, NX) and f.shape == rho.shape == mask.shape == (N, 8)
    assert np.allclose(rho[:, :2], 1e4) and np.allclose(rho[:, 2:4], 5.0)
    assert np.array_equal(np.asarray(mask[0]), [1, 1, 0, 0, 0, 0, 0, 0])
    assert np.array_equal(np.asarray(mask[1]), [1, 1, 1, 1, 1, 1, 1, 1])
    # hard rows: the cone and the (stage-1) speed rows, not the penalty
    assert np.array_equal(np.asarray(C.hard_mask([a, b, c])[1]), [1, 1, 0, 0, 1, 1, 1, 1])
    x = np.array([1.0, 0.0, 0.0, 0.05, 0.2, 0.0])
    m = C.block_margin(c, x)
    assert np.all(np.isinf(m[0])) and np.min(m[1]) == pytest.approx(0.1 - 0.2)
    with pytest.raises(ValueError, match="separately"):
        C.stack([a, C.thrust_box(1.0, N, nu=3)])
    with pytest.raises(ValueError, match="kind"):
        a.with_(kind="soft")


def test_bad_static_values():
    z = np.zeros((2, 2))
    with pytest.raises(ValueError, match="half_angle"):
        C.entry_cone(z, np.zeros(2), np.pi / 2, NX)
    with pytest.raises(ValueError, match="half_angle"):
        C.approach_cone(np.zeros((2, 3)), np.ones((2, 3)), 0.0, 4, 6)
    with pytest.raises(ValueError, match="n_faces"):
        C.approach_cone(np.zeros((2, 3)), np.ones((2, 3)), 0.3, 2, 6)
    with pytest.raises(ValueError, match="u_max"):
        C.thrust_box(-1.0, 2, nu=2)
    with pytest.raises(ValueError, match="offset"):
        C.rotating_hyperplane(z, np.zeros(2), -1.0, NX)
    with pytest.raises(ValueError, match="pos_index"):
        C.entry_cone(z, np.zeros(2), 0.3, NX, pos_index=(0, 7))
    with pytest.raises(ValueError, match="S"):
        C.ellipsoid_keep_out(z, z + 1, -np.eye(2), NX)


def test_jit_vmap_grad():
    """Every builder jits, vmaps over a batch and has finite gradients."""
    N = 3
    p = jnp.array([[2.0, 1.0], [1.5, -1.0], [-2.0, 0.3]])
    c = jnp.zeros((N, 2))
    ang = jnp.array([0.1, 0.2, 0.3])
    x = jnp.array([1.0, 2.0, 0.1, 0.01, -0.02, 0.0])

    def total(s):
        blocks = [
            C.ellipsoid_keep_out(p * s, c, jnp.eye(2) * s, NX),
            C.holding_radius(p, c, s, NX),
            C.entry_cone(p * s, ang * s, 0.3 * s, NX),
            C.rotating_hyperplane(c, ang * s, s, NX),
            C.overshoot(p * s, s, NX),
            C.velocity_bound(0.1 * s, N, NX, (3, 4)),
            C.approach_cone_penalty(p, ang, 0.3, s, NX),
        ]
        F, f, rho, _ = C.stack(blocks)
        u = C.thrust_box(jnp.array([1.0, 1.0]) * s, N)
        p3 = jnp.concatenate([p, jnp.ones((N, 1))], 1)
        b3 = C.approach_cone(p3 * s, p3, 0.4 * s, 4, 6)
        rh, _ = C.holding_radius_update(s, 0.01 * s, 0.01, 0.9, 0.1, 0.1, 0.2)
        return jnp.sum(rho * jax.nn.relu(F @ x - f)) + jnp.sum(u.f) + jnp.sum(b3.F @ x - b3.f) + rh

    g = jax.jit(jax.grad(total))(1.1)
    assert np.isfinite(g)
    gv = jax.jit(jax.vmap(jax.value_and_grad(total)))(jnp.array([0.9, 1.0, 1.2]))
    assert gv[0].shape == gv[1].shape == (3,)
    assert np.all(np.isfinite(gv[0])) and np.all(np.isfinite(gv[1]))
    assert np.isclose(gv[0][1], total(1.0))  # batched value matches the eager one


def test_exclusive_shares_rows_between_alternatives():
    N, nx = 4, 6
    rng = np.random.default_rng(0)

    def blk(m, kind, name, on=1.0):
        b = C.Block(
            F=jnp.asarray(rng.normal(size=(N, m, nx))),
            f=jnp.asarray(rng.normal(size=(N, m))),
            rho=jnp.asarray(rng.uniform(1, 2, size=(N, m))),
            mask=jnp.ones((N, m)),
            name=name,
            kind=kind,
        )
        return b.masked(on)

    alts = [
        [blk(1, "hard", "a"), blk(4, "penalty", "b", on=jnp.array([0, 0, 0, 1.0]))],
        [blk(4, "penalty", "c"), blk(1, "hard", "d")],
        [blk(4, "hard", "e"), blk(6, "hard", "f")],
    ]
    pick = jax.jit(lambda i: C.exclusive(alts, i))
    for i, alt in enumerate(alts):
        b = pick(i)
        assert b.F.shape == (N, 10, nx)  # the largest alternative's rows, not 16
        F, f, rho, mask = C.stack(alt)
        m = F.shape[1]
        np.testing.assert_array_equal(b.F[:, :m], F)
        np.testing.assert_array_equal(b.f[:, :m], f)
        np.testing.assert_array_equal(b.rho[:, :m], rho)
        np.testing.assert_array_equal(b.mask[:, :m], mask)
        assert np.all(b.mask[:, m:] == 0) and np.all(b.F[:, m:] == 0)
        # hardness follows the chosen alternative row by row
        want = C.hard_mask(alt)
        np.testing.assert_array_equal(C.hard_mask([b])[:, :m], want)
        assert np.all(C.hard_mask([b])[:, m:] == 0)
    with pytest.raises(ValueError, match="every alternative"):
        C.exclusive([alts[0], []], 0)
