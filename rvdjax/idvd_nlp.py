"""The IDVD trajectory and its NLP (paper 001 Eqs. 6-14): the polynomial parametrisation, a
solved plan (:class:`IDVDPlan`: its force, position and shifted warm start) and the CasADi/IPOPT
problem with its initial guess; the method and its choices are described in :mod:`rvdjax.idvd`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

_NPAR = 5  # a5, b5, da1, da2, db2
_EPS_D = 1e-6
_SMOOTH = 1e-3

# a_2..a_4 from [x(1) - a0 - a1 - a5, x'(1) - a1 - 5 a5, x''(1) - 20 a5] (k_f = 1)
_M_INV = np.linalg.inv(np.array([[1.0, 1.0, 1.0], [2.0, 3.0, 4.0], [2.0, 6.0, 12.0]]))


def _coeffs(a5, d1, d2, p0, v0, pf, vf, lib):
    """Degree-5 coefficients meeting x(0)=p0, xdot(0)=v0, x(1)=pf, xdot(1)=vf, xddot(1)=0."""
    a0 = p0
    a1 = d1 * v0
    tp1 = d1 + 2 * d2  # t'(1)
    tpp = 2 * d2  # t''
    rhs = [pf - a0 - a1 - a5, tp1 * vf - a1 - 5 * a5, tpp * vf - 20 * a5]
    a234 = [sum(_M_INV[r, c] * rhs[c] for c in range(3)) for r in range(3)]
    return [a0, a1, *a234, a5]


def _poly(c, k):
    """Value, first and second derivative of sum c_i k^i (works for numpy and CasADi)."""
    v = sum(ci * k**i for i, ci in enumerate(c))
    d = sum(i * ci * k ** (i - 1) for i, ci in enumerate(c) if i >= 1)
    dd = sum(i * (i - 1) * ci * k ** (i - 2) for i, ci in enumerate(c) if i >= 2)
    return v, d, dd


def _accel(c, d1, d2, k):
    """Real-time acceleration (Eq. 9d) and velocity of the component at virtual time k."""
    _, xp, xpp = _poly(c, k)
    tp = d1 + 2 * d2 * k
    tpp = 2 * d2
    return xpp / tp**2 - xp * tpp / tp**3, xp / tp


def _kappa_of_t(d1, d2, t, lib):
    """Inverse of t = d1 k + d2 k^2 (d1 > 0, d2 >= 0), numerically stable form."""
    return 2 * t / (d1 + lib.sqrt(d1**2 + 4 * d2 * t))


@dataclasses.dataclass(frozen=True)
class IDVDPlan:
    """A solved IDVD trajectory, starting at real time ``t0`` (absolute)."""

    ax: np.ndarray  # (6,) x coefficients in k
    ay: np.ndarray  # (6,) y coefficients in k
    dx: tuple  # (d_a1, d_a2)
    dy: tuple  # (d_b1, d_b2)
    t0: float
    tf: float  # duration t(k_f) of this plan [s]
    cost: float  # NLP objective (planned L1 effort) [N s]
    success: bool
    status: str
    iterations: int
    z: np.ndarray  # decision vector (warm start)
    lam_x: np.ndarray | None = None  # bound multipliers (IPOPT warm start)
    lam_g: np.ndarray | None = None  # constraint multipliers (IPOPT warm start)
    feasible: bool = True  # bounds and constraints hold to 1e-6 (also when not converged)

    def force(self, t, mass):
        """Planned force (2,) at absolute time t (held at zero after the plan ends)."""
        tau = t - self.t0
        if tau >= self.tf or tau < 0:
            return np.zeros(2)
        kx = _kappa_of_t(*self.dx, tau, np)
        ky = _kappa_of_t(*self.dy, tau, np)
        ux, _ = _accel(self.ax, *self.dx, kx)
        uy, _ = _accel(self.ay, *self.dy, ky)
        return mass * np.array([ux, uy])

    def shifted(self, t, mass, u_max, S):
        """Decision vector of the remaining part of this plan, re-parametrised to start at
        absolute time ``t`` (a warm start for a re-plan: with k = k_t + (1 - k_t) k', a
        degree-5 polynomial stays degree 5 with a_5' = a_5 (1 - k_t)^5, and the time map
        d_1 k + d_2 k^2 becomes d_1' = (1 - k_t)(d_1 + 2 d_2 k_t), d_2' = d_2 (1 - k_t)^2).
        The slacks are the plan's |u| at the new points."""
        tau = min(max(t - self.t0, 0.0), self.tf)
        kx = float(_kappa_of_t(*self.dx, tau, np))
        ky = float(_kappa_of_t(*self.dy, tau, np))
        (d1, d2), (e1, e2) = self.dx, self.dy
        z = [
            self.ax[5] * (1 - kx) ** 5,
            self.ay[5] * (1 - ky) ** 5,
            max((1 - kx) * (d1 + 2 * d2 * kx), _EPS_D),
            max(d2 * (1 - kx) ** 2, _EPS_D),
            max(e2 * (1 - ky) ** 2, _EPS_D),
        ]
        k = np.linspace(0.0, 1.0, S)
        ux = mass * _accel(self.ax, d1, d2, kx + (1 - kx) * k)[0]
        uy = mass * _accel(self.ay, e1, e2, ky + (1 - ky) * k)[0]
        return np.r_[z, np.minimum(np.abs(ux) + 1e-9, u_max), np.minimum(np.abs(uy) + 1e-9, u_max)]

    def position(self, t):
        tau = np.clip(np.asarray(t, float) - self.t0, 0.0, self.tf)
        kx = _kappa_of_t(*self.dx, tau, np)
        ky = _kappa_of_t(*self.dy, tau, np)
        return np.stack([_poly(self.ax, kx)[0], _poly(self.ay, ky)[0]], axis=-1)


class _NLP:
    """CasADi/IPOPT IDVD problem with parameters (x, y, vx, vy, time budget)."""

    def __init__(
        self,
        dock,
        obstacle,
        r_obs,
        axis,
        half,
        cone_range,
        u_max,
        mass,
        S,
        max_iter,
        cone=True,
        warm=False,
    ):
        import casadi as ca

        z = ca.SX.sym("z", _NPAR)
        sx = ca.SX.sym("sx", S)
        sy = ca.SX.sym("sy", S)
        par = ca.SX.sym("p", 5)
        a5, b5, da1, da2, db2 = (z[i] for i in range(_NPAR))
        T = da1 + da2
        db1 = T - db2
        cx = _coeffs(a5, da1, da2, par[0], par[2], dock[0], 0.0, ca)
        cy = _coeffs(b5, db1, db2, par[1], par[3], dock[1], 0.0, ca)
        k = np.linspace(0.0, 1.0, S)
        w = np.full(S, 1.0 / (S - 1))
        w[[0, -1]] *= 0.5
        g, lbg, ubg = [], [], []
        cost = 0
        for j in range(S):
            kj = float(k[j])
            ux = mass * _accel(cx, da1, da2, kj)[0]
            uy = mass * _accel(cy, db1, db2, kj)[0]
            cost += w[j] * (sx[j] * (da1 + 2 * da2 * kj) + sy[j] * (db1 + 2 * db2 * kj))
            g += [sx[j] - ux, sx[j] + ux, sy[j] - uy, sy[j] + uy]
            lbg += [0.0] * 4
            ubg += [ca.inf] * 4
            # geometry at common real time t_j = t_x(k_j)
            tj = da1 * kj + da2 * kj**2
            kyj = _kappa_of_t(db1, db2, tj, ca)
            r = ca.vertcat(_poly(cx, kj)[0], _poly(cy, kyj)[0])
            dr = r - ca.DM(obstacle)
            g.append(ca.dot(dr, dr) - r_obs**2)
            lbg.append(0.0)
            ubg.append(ca.inf)
            e = r - ca.DM(dock)
            dist = ca.sqrt(ca.dot(e, e) + 1e-12)
            row1 = ca.sin(axis + half) * e[0] - ca.cos(axis + half) * e[1]  # >= 0
            row2 = -(ca.sin(axis - half) * e[0] - ca.cos(axis - half) * e[1])  # >= 0
            for row in (row1, row2) if cone else ():
                b = dist - cone_range
                smax = 0.5 * (row + b + ca.sqrt((row - b) ** 2 + _SMOOTH**2))
                g.append(smax)
                lbg.append(0.0)
                ubg.append(ca.inf)
        g += [T - par[4], db1]  # t_f <= budget, d_b1 > 0
        lbg += [-ca.inf, _EPS_D]
        ubg += [0.0, ca.inf]
        self.S = S
        self.lbx = [-ca.inf, -ca.inf, _EPS_D, _EPS_D, _EPS_D] + [0.0] * (2 * S)
        self.ubx = [ca.inf] * _NPAR + [u_max] * (2 * S)
        self.lbg, self.ubg = lbg, ubg
        self._coef = ca.Function("coef", [z, par], [ca.vertcat(*cx), ca.vertcat(*cy), db1])
        nlp = {"x": ca.vertcat(z, sx, sy), "p": par, "f": cost, "g": ca.vertcat(*g)}
        self._g = ca.Function("g", [nlp["x"], par], [nlp["g"]])
        opts = {
            "ipopt.print_level": 0,
            "print_time": False,
            "ipopt.max_iter": max_iter,
            "ipopt.tol": 1e-8,
            "ipopt.sb": "yes",
        }
        if warm:  # paper 001: "Using the IPOPT warm start capabilities" (primal and dual)
            opts.update(
                {
                    "ipopt.warm_start_init_point": "yes",
                    "ipopt.mu_init": 1e-6,
                    "ipopt.warm_start_bound_push": 1e-9,
                    "ipopt.warm_start_bound_frac": 1e-9,
                    "ipopt.warm_start_slack_bound_push": 1e-9,
                    "ipopt.warm_start_slack_bound_frac": 1e-9,
                    "ipopt.warm_start_mult_bound_push": 1e-9,
                }
            )
        self.solver = ca.nlpsol("idvd", "ipopt", nlp, opts)

    def solve(self, state, budget, t0, x_init, lam_x=None, lam_g=None):
        par = np.r_[state, budget]
        warm = {} if lam_x is None else {"lam_x0": lam_x, "lam_g0": lam_g}
        sol = self.solver(
            x0=x_init, p=par, lbx=self.lbx, ubx=self.ubx, lbg=self.lbg, ubg=self.ubg, **warm
        )
        st = self.solver.stats()
        x = np.asarray(sol["x"]).ravel()
        g = np.asarray(self._g(x, par)).ravel()
        tol = 1e-6
        feasible = bool(
            np.all(np.isfinite(x))
            and np.all(x >= np.asarray(self.lbx) - tol)
            and np.all(x <= np.asarray(self.ubx) + tol)
            and np.all(g >= np.asarray(self.lbg) - tol)
            and np.all(g <= np.asarray(self.ubg) + tol)
        )
        z = x[:_NPAR]
        cx, cy, db1 = (np.asarray(v).ravel() for v in self._coef(z, par))
        return IDVDPlan(
            ax=cx,
            ay=cy,
            dx=(float(z[2]), float(z[3])),
            dy=(float(db1[0]), float(z[4])),
            t0=float(t0),
            tf=float(z[2] + z[3]),
            cost=float(sol["f"]),
            success=bool(st["success"]),
            status=str(st["return_status"]),
            iterations=int(st["iter_count"]),
            z=x,
            lam_x=np.asarray(sol["lam_x"]).ravel(),
            lam_g=np.asarray(sol["lam_g"]).ravel(),
            feasible=feasible,
        )


def _initial_guess(state, dock, budget, S, side=1.0):
    """a_5 / b_5 of opposite signs bend the path around the obstacle on one side."""
    bend = side * 2.0 * np.linalg.norm(np.asarray(state[:2]) - dock) / 2.8
    return np.r_[bend, -bend, 0.45 * budget, 0.45 * budget, 0.45 * budget, np.full(2 * S, 1e-3)]
