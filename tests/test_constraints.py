"""Geometric tests of the constraint library (rvdjax.constraints)."""

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


def _rowval(Fx, fx, p, t=0, nx=NX, pos=POS):
    """Row slack Fx x - fx at position p (positive = violated)."""
    return np.asarray(Fx[t]) @ _state(p, nx, pos) - np.asarray(fx[t])


def test_thrust_box():
    Fu, fu = C.thrust_box_rows(np.array([1.0, 2.0, 0.5]), N=3)
    assert Fu.shape == (3, 6, 3) and fu.shape == (3, 6)
    u_in, u_out = np.array([0.9, -1.9, 0.4]), np.array([0.0, 2.1, 0.0])
    assert np.all(np.asarray(Fu[1]) @ u_in <= fu[1])
    assert np.any(np.asarray(Fu[1]) @ u_out > fu[1])
    assert C.thrust_box_rows(0.3, N=2, nu=2)[0].shape == (2, 4, 2)


@pytest.mark.parametrize("three_d", [False, True])
def test_ellipsoid_keepout_tangent_and_conservative(three_d):
    d = 3 if three_d else 2
    nx, pos = (6, (0, 1, 2)) if three_d else (NX, POS)
    N = 4
    L = RNG.normal(size=(d, d))
    S = L @ L.T + 0.5 * np.eye(d)
    centres = RNG.normal(size=(N, d))
    guess = centres + 3.0 * RNG.normal(size=(N, d))
    Fx, fx = C.ellipsoid_keepout_rows(guess, centres, S, nx, pos)
    assert Fx.shape == (N, 1, nx) and fx.shape == (N, 1)
    Fx, fx = np.asarray(Fx), np.asarray(fx)
    for t in range(N):
        dl = guess[t] - centres[t]
        r0 = centres[t] + dl / np.sqrt(dl @ S @ dl)
        assert abs(_rowval(Fx, fx, r0, t, nx, pos)[0]) < 1e-9  # tangent at r0
        assert _rowval(Fx, fx, guess[t], t, nx, pos)[0] < 0  # guess outside is accepted
        # points inside the ellipsoid violate the row
        z = RNG.normal(size=(200, d))
        z *= (RNG.uniform(size=(200, 1)) ** (1 / d)) / np.linalg.norm(z, axis=1, keepdims=True)
        inside = centres[t] + z @ np.linalg.inv(np.linalg.cholesky(S)) * 0.999
        assert np.all(np.einsum("ki,ij,kj->k", inside - centres[t], S, inside - centres[t]) < 1)
        assert all(_rowval(Fx, fx, p, t, nx, pos)[0] > 0 for p in inside)
        # every feasible point of the half-space lies outside the ellipsoid
        pts = centres[t] + 5.0 * RNG.uniform(-1, 1, size=(2000, d))
        ok = np.array([_rowval(Fx, fx, p, t, nx, pos)[0] <= 0 for p in pts])
        q = np.einsum("ki,ij,kj->k", pts - centres[t], S, pts - centres[t])
        assert ok.any() and np.all(q[ok] >= 1 - 1e-9)


def test_ellipsoid_degenerate_guess_finite():
    Fx, fx = C.ellipsoid_keepout_rows(np.zeros((2, 2)), np.zeros((2, 2)), np.eye(2), NX)
    assert np.all(np.isfinite(Fx)) and np.all(np.isfinite(fx))


def test_holding_radius_rows():
    N = 3
    tgt = RNG.normal(size=(N, 2))
    guess = tgt + np.array([[2.0, 1.0], [0.0, -3.0], [-1.0, 0.5]])
    r = np.array([1.0, 1.5, 0.8])
    Fx, fx = C.holding_radius_rows(guess, tgt, r, NX, POS)
    for t in range(N):
        u = (guess[t] - tgt[t]) / np.linalg.norm(guess[t] - tgt[t])
        assert abs(_rowval(Fx, fx, tgt[t] + r[t] * u, t)[0]) < 1e-9
        assert _rowval(Fx, fx, tgt[t] + 0.9 * r[t] * u, t)[0] > 0
        assert _rowval(Fx, fx, tgt[t], t)[0] > 0
    with pytest.raises(ValueError, match="r_hold"):
        C.holding_radius_rows(guess, tgt, -1.0, NX)


def test_holding_radius_update_rule():
    kw = dict(gamma=0.9, eta=0.1, zeta=0.2, r_min=0.5)
    upd = lambda r, pe, ae: float(C.holding_radius_update(r, pe, ae, **kw))  # noqa: E731
    assert upd(1.0, [0.05, 0.0], 0.1) == pytest.approx(0.9)  # both conditions: shrink
    assert upd(1.0, [0.2, 0.0], 0.1) == pytest.approx(1.0)  # position error too large
    assert upd(1.0, [0.05, 0.0], 0.3) == pytest.approx(1.0)  # attitude error too large
    assert upd(1.0, [0.05, 0.0], 2 * np.pi + 0.1) == pytest.approx(0.9)  # angle wrapped
    assert upd(0.52, [0.0, 0.0], 0.0) == pytest.approx(0.5)  # floored at r_min
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
    Fx, fx = C.entry_cone_rows(port, np.full(N, a), h, NX, POS)
    assert Fx.shape == (N, 2, NX)
    for t in range(N):
        for b in np.linspace(-0.95 * h, 0.95 * h, 7):
            for s in (0.01, 1.0, 10.0):
                p = port[t] + s * np.array([np.cos(a + b), np.sin(a + b)])
                assert np.all(_rowval(Fx, fx, p, t) <= 1e-12)
        for b in (1.1 * h, -1.1 * h, np.pi / 2, np.pi, np.pi - 0.5 * h):
            p = port[t] + 1.0 * np.array([np.cos(a + b), np.sin(a + b)])
            assert np.any(_rowval(Fx, fx, p, t) > 0)
        assert np.allclose(_rowval(Fx, fx, port[t], t), 0.0)  # apex on both planes


@pytest.mark.parametrize("inscribed", [False, True])
def test_approach_cone_3d(inscribed):
    N, h, k = 2, np.deg2rad(30), 4
    port = RNG.normal(size=(N, 3))
    axis = RNG.normal(size=(N, 3))
    Fx, fx = C.approach_cone_rows_3d(port, axis, h, k, 6, (0, 1, 2), inscribed=inscribed)
    assert Fx.shape == (N, k, 6)
    pos = (0, 1, 2)
    for t in range(N):
        a = axis[t] / np.linalg.norm(axis[t])
        v = RNG.normal(size=(400, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        ang = np.arccos(np.clip(v @ a, -1, 1))
        feas = np.array([np.all(_rowval(Fx, fx, port[t] + 2 * vi, t, 6, pos) <= 1e-12) for vi in v])
        if inscribed:  # polyhedron inside the cone
            assert np.all(ang[feas] <= h + 1e-9)
        else:  # cone inside the polyhedron
            assert np.all(feas[ang <= h])
        assert not np.any(feas[ang > np.pi / 2])  # nothing behind the port
        assert np.all(_rowval(Fx, fx, port[t] + a, t, 6, pos) < 0)  # axis strictly inside


def test_approach_cone_penalty():
    port, ang = np.zeros((3, 2)), np.array([0.0, 0.1, 0.2])
    Fx, fx, rho, mask = C.approach_cone_penalty_rows(
        port, ang, 0.3, 7.0, NX, POS, terminal_only=True
    )
    assert np.all(rho == 7.0) and Fx.shape == (3, 2, NX)
    assert np.array_equal(np.asarray(mask), [[0, 0], [0, 0], [1, 1]])
    Fe, fe = C.entry_cone_rows(port, ang, 0.3, NX, POS)
    assert np.allclose(Fx, Fe) and np.allclose(fx, fe)
    with pytest.raises(ValueError, match="lam"):
        C.approach_cone_penalty_rows(port, ang, 0.3, 0.0, NX)


def test_rotating_hyperplane_rows():
    N = 3
    c = RNG.normal(size=(N, 2))
    phi = np.array([0.3, 1.5, -2.0])
    Fx, fx = C.rotating_hyperplane_rows(c, phi, 1.2, NX, POS)
    for t in range(N):
        n = np.array([np.cos(phi[t]), np.sin(phi[t])])
        assert abs(_rowval(Fx, fx, c[t] + 1.2 * n, t)[0]) < 1e-12  # tangent point
        assert _rowval(Fx, fx, c[t] + 2.0 * n, t)[0] < 0
        assert _rowval(Fx, fx, c[t], t)[0] > 0
        z = RNG.uniform(-1, 1, size=(300, 2)) * 1.2
        z = z[np.linalg.norm(z, axis=1) < 1.2]
        assert all(_rowval(Fx, fx, c[t] + zi, t)[0] > 0 for zi in z)  # circle excluded


@pytest.mark.parametrize("direction", [0, 1, -1])
def test_hyperplane_angles_capped_monotone(direction):
    ts, rate, N = 2.0, 0.01, 30
    th0, thf = 0.2, 2.0
    phi = np.asarray(C.hyperplane_angles(th0, thf, N, ts, rate, direction=direction))
    steps = np.diff(np.concatenate([[th0], phi]))
    assert np.all(np.abs(steps) <= rate * ts + 1e-12)
    assert np.all(steps * np.sign(steps[0]) >= -1e-15)  # monotone
    if direction == -1:
        assert steps[0] < 0
    else:
        assert steps[0] > 0
    # uncapped: reaches theta_final exactly at the end of the horizon and stays
    phi2 = np.asarray(C.hyperplane_angles(th0, thf, N, ts, 10.0))
    assert np.allclose(np.diff(np.concatenate([[th0], phi2])), (thf - th0) / N)
    phi3 = np.asarray(C.hyperplane_angles(th0, thf, N, ts, 10.0, t0=100.0))
    assert np.isclose(phi3[-1], thf)  # uniform rate from the rotation start to horizon end
    assert np.allclose(np.diff(phi3), ts * (thf - th0) / (100.0 + N * ts))
    # capped but long horizon: stops at theta_final, never overshoots
    phi4 = np.asarray(C.hyperplane_angles(th0, thf, 200, ts, rate))
    assert np.isclose(phi4[-1], thf) and np.all(phi4 <= thf + 1e-12)
    with pytest.raises(ValueError, match="rate_max"):
        C.hyperplane_angles(th0, thf, N, ts, 0.0)


def test_overshoot_and_velocity_rows():
    n = np.array([[0.0, 2.0], [1.0, 1.0]])
    tgt = np.array([[1.0, 1.0], [0.0, 0.0]])
    Fx, fx = C.overshoot_row(n, 0.5, NX, POS, target_pos=tgt)
    assert _rowval(Fx, fx, [1.0, 1.6], 0)[0] < 0 and _rowval(Fx, fx, [5.0, 1.4], 0)[0] > 0
    assert abs(_rowval(Fx, fx, 0.5 * np.array([1, 1]) / np.sqrt(2), 1)[0]) < 1e-12
    Fv, fv = C.velocity_bound_rows(0.1, 2, NX, (3, 4, 5))
    assert Fv.shape == (2, 6, NX)
    x_ok, x_bad = np.array([9, 9, 9, 0.05, -0.09, 0.0]), np.array([0, 0, 0, 0, -0.11, 0])
    assert np.all(np.asarray(Fv[0]) @ x_ok <= fv[0])
    assert np.any(np.asarray(Fv[1]) @ x_bad > fv[1])
    with pytest.raises(ValueError, match="v_max"):
        C.velocity_bound_rows(-0.1, 2, NX, (3, 4))
    with pytest.raises(ValueError, match="vel_index"):
        C.velocity_bound_rows(0.1, 2, NX, (3, 9))


def test_target_frame_and_hold_point():
    N = 3
    port_b = np.array([0.4, 0.1])
    tgt = RNG.normal(size=(N, 2))
    th = np.array([0.0, 1.0, -2.5])
    port, ax = C.target_frame(port_b, tgt, th)
    for t in range(N):
        R = np.array([[np.cos(th[t]), -np.sin(th[t])], [np.sin(th[t]), np.cos(th[t])]])
        assert np.allclose(port[t], tgt[t] + R @ port_b)
        e = np.array([np.cos(ax[t]), np.sin(ax[t])])
        assert np.allclose(e, R @ port_b / np.linalg.norm(port_b))
    hp = C.hold_point(port, ax, 1.5, target_pos=tgt)
    assert np.allclose(np.linalg.norm(hp - tgt, axis=1), 1.5)
    assert np.allclose(C.hold_point(port, ax, 1.0), port + np.stack([np.cos(ax), np.sin(ax)], 1))
    # 3-D: rotation about x
    p3, a3 = C.target_frame(np.array([0.0, 1.0, 0.0]), np.zeros((N, 3)), th)
    for t in range(N):
        Rx = np.array(
            [[1, 0, 0], [0, np.cos(th[t]), -np.sin(th[t])], [0, np.sin(th[t]), np.cos(th[t])]]
        )
        assert np.allclose(p3[t], Rx @ [0, 1, 0]) and np.allclose(a3[t], Rx @ [0, 1, 0])
    assert np.allclose(C.target_angles(0.1, 0.02, 3, 2.0), 0.1 + 0.02 * np.array([2, 4, 6]))


def test_stack_rows():
    N = 2
    a = C.entry_cone_rows(np.zeros((N, 2)), np.zeros(N), 0.3, NX)
    b = C.approach_cone_penalty_rows(
        np.zeros((N, 2)), np.zeros(N), 0.3, 5.0, NX, terminal_only=True
    )
    F, f, rho, mask = C.stack_rows(a, b, rho=1e4, pad_to=7)
    assert F.shape == (N, 7, NX) and f.shape == rho.shape == mask.shape == (N, 7)
    assert np.allclose(rho[:, :2], 1e4) and np.allclose(rho[:, 2:4], 5.0)
    assert np.array_equal(np.asarray(mask[0]), [1, 1, 0, 0, 0, 0, 0])
    assert np.array_equal(np.asarray(mask[1]), [1, 1, 1, 1, 0, 0, 0])
    with pytest.raises(ValueError, match="pad_to"):
        C.stack_rows(a, pad_to=1)


def test_bad_static_values():
    z = np.zeros((2, 2))
    with pytest.raises(ValueError, match="half_angle"):
        C.entry_cone_rows(z, np.zeros(2), np.pi / 2, NX)
    with pytest.raises(ValueError, match="half_angle"):
        C.approach_cone_rows_3d(np.zeros((2, 3)), np.ones((2, 3)), 0.0, 4, 6)
    with pytest.raises(ValueError, match="n_faces"):
        C.approach_cone_rows_3d(np.zeros((2, 3)), np.ones((2, 3)), 0.3, 2, 6)
    with pytest.raises(ValueError, match="u_max"):
        C.thrust_box_rows(-1.0, 2, nu=2)
    with pytest.raises(ValueError, match="offset"):
        C.rotating_hyperplane_rows(z, np.zeros(2), -1.0, NX)
    with pytest.raises(ValueError, match="pos_index"):
        C.entry_cone_rows(z, np.zeros(2), 0.3, NX, pos_index=(0, 7))
    with pytest.raises(ValueError, match="S"):
        C.ellipsoid_keepout_rows(z, z + 1, -np.eye(2), NX)


def test_jit_vmap_grad():
    """Every builder jits, vmaps over a batch and has finite gradients."""
    N = 3
    p = jnp.array([[2.0, 1.0], [1.5, -1.0], [-2.0, 0.3]])
    c = jnp.zeros((N, 2))
    ang = jnp.array([0.1, 0.2, 0.3])
    x = jnp.array([1.0, 2.0, 0.1, 0.01, -0.02, 0.0])

    def total(s):
        rows = [
            C.ellipsoid_keepout_rows(p * s, c, jnp.eye(2) * s, NX),
            C.holding_radius_rows(p, c, s, NX),
            C.entry_cone_rows(p * s, ang * s, 0.3 * s, NX),
            C.rotating_hyperplane_rows(
                c, C.hyperplane_angles(0.1 * s, 2.0, N, 1.0, 0.05 * s), s, NX
            ),
            C.overshoot_row(p * s, s, NX),
            C.velocity_bound_rows(0.1 * s, N, NX, (3, 4)),
            C.approach_cone_penalty_rows(p, ang, 0.3, s, NX)[:2],
        ]
        F, f, _, _ = C.stack_rows(*rows)
        pp, aa = C.target_frame(jnp.array([0.3, 0.0]) * s, c, ang * s)
        hp = C.hold_point(pp, aa, s, target_pos=c)
        Fu, fu = C.thrust_box_rows(jnp.array([1.0, 1.0]) * s, N)
        p3 = jnp.concatenate([p, jnp.ones((N, 1))], 1)
        F3, f3 = C.approach_cone_rows_3d(p3 * s, p3, 0.4 * s, 4, 6)
        rh = C.holding_radius_update(s, 0.01 * s, 0.01, 0.9, 0.1, 0.1, 0.2)
        return (
            jnp.sum(jax.nn.relu(F @ x - f)) + jnp.sum(hp) + jnp.sum(fu) + jnp.sum(F3 @ x - f3) + rh
        )

    g = jax.jit(jax.grad(total))(1.1)
    assert np.isfinite(g)
    gv = jax.jit(jax.vmap(jax.value_and_grad(total)))(jnp.array([0.9, 1.0, 1.2]))
    assert gv[0].shape == gv[1].shape == (3,)
    assert np.all(np.isfinite(gv[0])) and np.all(np.isfinite(gv[1]))
    assert np.isclose(gv[0][1], total(1.0))  # batched value matches the eager one
