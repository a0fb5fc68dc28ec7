# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # rvdjax quickstart
#
# This notebook walks through the main uses of `rvdjax`, a Fast MPC solver (log barrier +
# infeasible-start Newton, Riccati-structured steps) for spacecraft rendezvous guidance in JAX:
#
# 1. build the first MPC step of the `fastmpc-3d` scenario (paper 000, Table 1),
# 2. solve it in the two modes (`accurate` and `paper`),
# 3. check the answer against Clarabel,
# 4. solve a batch of 64 perturbed problems in one `jax.vmap`-ed call,
# 5. differentiate the planned Δv with respect to the input weight R.
#
# It is a plain Python script in jupytext "percent" format: open it in Jupyter (with jupytext)
# or run it top to bottom with `python notebooks/quickstart.py` (under a minute on a laptop,
# most of it compilation).

# %%
import time

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import rvdjax  # noqa: F401  (enables float64 in JAX)
from rvdjax.peers import solve_clarabel
from rvdjax.problems import (
    FASTMPC3D,
    fastmpc3d_first_step,
    fastmpc3d_first_step_batch,
    perturbed_x0,
)
from rvdjax.qp import split_solution, to_qp
from rvdjax.solver import SolverParams, SolverSettings, Status, max_violation, solve

# %% [markdown]
# ## 1. The problem
#
# Clohessy–Wiltshire dynamics at 705 km altitude, a 6500 kg chaser, zero-order hold at
# Ts = 15 s, horizon N = 30, |u_i| <= 20 N per axis, a DARE terminal weight, and two moving
# spherical keep-out zones linearised into one half-space row per zone and stage. The rows
# are *soft* (exact L1 penalty rho = 1e8), so a plan exists even if noise pushes the chaser
# inside a zone.
#
# `fastmpc3d_first_step` returns an `OCP`: a NamedTuple of stage-wise arrays, i.e. a JAX
# pytree that can be jitted, vmapped and differentiated.

# %%
ocp = fastmpc3d_first_step()
print(
    f"N = {ocp.N}, nx = {ocp.nx}, nu = {ocp.nu}, input rows/stage = {ocp.mu}, "
    f"state rows/stage = {ocp.mx}"
)
print("x0 =", np.asarray(ocp.x0))

# %% [markdown]
# ## 2. Solve in both modes
#
# * `SolverSettings()` (accurate): barrier continuation until the duality gap is below 1e-9
#   relative; matches an interior-point QP solver.
# * `SolverSettings.paper()`: the published algorithm, fixed kappa = 0.05 (a traced
#   `SolverParams` value) and at most 10 Newton
#   steps; fast, feasible, but not optimal.
#
# `solve` is jitted (the settings are static); the first call per setting compiles.

# %%
accurate = SolverSettings()
paper = SolverSettings.paper()
sols = {}
for name, settings in (("accurate", accurate), ("paper", paper)):
    t0 = time.perf_counter()
    sol = jax.block_until_ready(solve(ocp, settings))
    t_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    sol = jax.block_until_ready(solve(ocp, settings))
    t_again = time.perf_counter() - t0
    sols[name] = sol
    print(
        f"{name:9s} objective {float(sol.objective):.6e}  iterations {int(sol.iterations):3d}  "
        f"status {Status.name(int(sol.status)):9s}  first call {t_first:.2f} s, "
        f"then {1e3 * t_again:.2f} ms"
    )

# %% [markdown]
# ## 3. Compare with Clarabel
#
# `to_qp(ocp, soft=False)` assembles the sparse hard-constrained QP of the papers;
# `solve_clarabel` solves it with tight tolerances.

# %%
ref = solve_clarabel(to_qp(ocp, soft=False))
print(f"Clarabel  objective {ref.objective:.6e}  status {ref.status}")
for name, sol in sols.items():
    gap = (float(sol.objective) - ref.objective) / abs(ref.objective)
    viol = float(max_violation(ocp, sol.u, sol.x))
    print(f"{name:9s} relative gap {gap:+.2e}, max constraint violation {viol:.1e}")
assert abs(float(sols["accurate"].objective) - ref.objective) <= 1e-6 * abs(ref.objective)

# %% [markdown]
# The two plans in the orbital plane (radial x against along-track y), with Clarabel's optimum.

# %%
fig, ax = plt.subplots(figsize=(6, 4))
for name, sol in sols.items():
    x = np.vstack([np.asarray(ocp.x0), np.asarray(sol.x)])
    ax.plot(x[:, 1], x[:, 0], "-o", ms=2.5, label=name)
_, x_clarabel = split_solution(ref.z, ocp.N, ocp.nx, ocp.nu)
x_ref = np.vstack([np.asarray(ocp.x0), x_clarabel])
ax.plot(x_ref[:, 1], x_ref[:, 0], "k--", lw=1, label="Clarabel")
ax.plot([0], [0], "ks", label="target")
ax.set_xlabel("along-track y [m]")
ax.set_ylabel("radial x [m]")
ax.legend(fontsize=8)
plt.show()

# %% [markdown]
# ## 4. A batch: 64 perturbed initial states in one call
#
# `fastmpc3d_first_step_batch` stacks 64 problems (every field gets a leading batch axis);
# `jax.vmap(solve)` solves them in one compiled program. Each problem has its own status.

# %%
x0s = perturbed_x0(0, 64)
batch = fastmpc3d_first_step_batch(x0s)
solve_batch = jax.jit(jax.vmap(lambda o: solve(o, accurate)))
t0 = time.perf_counter()
bsol = jax.block_until_ready(solve_batch(batch))
print(f"first call (compile + solve): {time.perf_counter() - t0:.2f} s")
t0 = time.perf_counter()
bsol = jax.block_until_ready(solve_batch(batch))
dt = time.perf_counter() - t0
print(f"64 problems in {1e3 * dt:.1f} ms ({1e3 * dt / 64:.2f} ms per problem)")
counts = np.bincount(np.asarray(bsol.status), minlength=len(Status.names))
print("status counts:", {name: int(c) for name, c in zip(Status.names, counts, strict=True)})
print(
    "iterations: median",
    int(np.median(np.asarray(bsol.iterations))),
    "max",
    int(np.max(np.asarray(bsol.iterations))),
)

# %% [markdown]
# ## 5. Gradient of the planned Δv with respect to the R weight
#
# The planned velocity change is Δv = Σ_t Σ_i |u_{t,i}| Ts / m. Its smooth version,
# with |u| ≈ sqrt(u² + ε²), is differentiable in the problem data. `solve` has an implicit
# derivative (one extra structured KKT solve, no backpropagation through the Newton loop),
# valid at the barrier solution for the kappa it returns. For a smooth, well-defined map,
# use a **fixed kappa** solved to convergence (paper mode with many iterations) rather than
# the accurate mode, whose kappa depends on the data.
#
# We differentiate with respect to log s, where R -> s R scales the input weight.

# %%
ts, mass = FASTMPC3D["ts"], FASTMPC3D["mass"]
fixed_kappa = SolverSettings(mode="paper", max_iter=200)
kappa = SolverParams(kappa=0.05, tol=1e-12).checked()  # traced: no recompile on change
EPS = 1e-3  # [N] smoothing of |u|


def planned_dv(log_r_scale):
    scaled = ocp._replace(R=ocp.R * jnp.exp(log_r_scale))
    sol = solve(scaled, fixed_kappa, params=kappa)
    return jnp.sum(jnp.sqrt(sol.u**2 + EPS**2)) * ts / mass, sol.status


sol_fixed = solve(ocp, fixed_kappa, params=kappa)
print(
    f"fixed-kappa solve: status {Status.name(int(sol_fixed.status))}, "
    f"{int(sol_fixed.iterations)} iterations"
)
dv_exact = float(jnp.sum(jnp.abs(sol_fixed.u)) * ts / mass)
print(f"planned Δv = {dv_exact:.5f} m/s")

value_and_grad = jax.jit(jax.value_and_grad(planned_dv, has_aux=True))
(dv, status), g = value_and_grad(0.0)
print(f"smooth Δv = {float(dv):.5f} m/s, d Δv / d log(R scale) = {float(g):+.5f} m/s")

# Check against a central finite difference (forward solves only).
h = 1e-4
fd = (float(planned_dv(h)[0]) - float(planned_dv(-h)[0])) / (2 * h)
print(f"finite difference: {fd:+.5f} m/s  (relative difference {abs(fd - g) / abs(fd):.1e})")
assert int(status) == Status.CONVERGED
assert abs(fd - float(g)) <= 1e-4 * abs(fd)

# %% [markdown]
# A heavier input weight (larger R) trades thrust for tracking error, so the planned Δv
# falls as R grows: the gradient is negative. The same `jax.grad` works through
# `jax.vmap` (a batch of gradients), and with respect to any float field of the OCP (x0,
# Q, the dynamics A and B, the constraint rows, rho), or upstream of it, e.g. through
# `rvdjax.dynamics.discretize_zoh` and `dare` to the sampling time.
