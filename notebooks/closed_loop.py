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
# # Closed-loop guidance with rvdjax
#
# 1. fly a named scenario (paper 002's rotating target, case B) in closed loop and look at it,
# 2. fly it in paper mode (paper 000's Algorithm 1) next to the accurate mode,
# 3. fly 16 disturbed copies in one `vmap` (navigation noise and the Gauss–Markov thrust error
#    of paper 003 Ch. 5, one PRNG key each) and look at the spread.
#
# Run it with `python notebooks/closed_loop.py` (about a minute, most of it compilation).

# %%
import dataclasses

import jax
import matplotlib.pyplot as plt
import numpy as np

import rvdjax  # noqa: F401  (enables float64 in JAX)
from rvdjax.plots import plot_docking
from rvdjax.scenarios import get_scenario
from rvdjax.solver import Status

sc = get_scenario("rotating-target-b")
params, x0 = sc.build()
sc.validate(params, x0, sc.config)
print(sc.description, f"[{sc.source}]")

# %% [markdown]
# ## 1. One maneuver
#
# `sc.fly(params, x0, config)` is the whole closed loop as one `lax.scan`: a pure function of
# arrays, so `jax.jit` compiles it once.

# %%
fly = jax.jit(lambda p, x: sc.fly(p, x, sc.config))
infos, m = fly(params, x0)
print(
    f"docked {bool(m.docked)} after {float(m.time_to_dock_s):.0f} s, "
    f"effort {float(m.effort_l1_N_s):.3f} N s, keep-out/cone violation "
    f"{float(m.max_violation_m):.1e} m, statuses {np.asarray(m.status_counts)}"
)
assert bool(m.docked) and float(m.max_violation_m) == 0.0
plot_docking("rotating_target_b.png", sc, params, infos)  # trajectory, thrust, r_hold

# %% [markdown]
# ## 2. Paper mode
#
# Paper 000's Algorithm 1: a fixed barrier weight kappa and at most 10 Newton steps per MPC
# step. `sc.settings("paper")` carries the scenario's kappa (here 6.25e-3: with 0.05 the
# barrier holds the chaser ~0.1 m off the port, see the README).

# %%
paper = dataclasses.replace(sc.config, settings=sc.settings("paper"))
_, mp = jax.jit(lambda p, x: sc.fly(p, x, paper))(params, x0)
counts = np.asarray(mp.status_counts)
print(
    f"paper mode (kappa {sc.paper_kappa:g}): docked {bool(mp.docked)} after "
    f"{float(mp.time_to_dock_s):.0f} s, effort {float(mp.effort_l1_N_s):.3f} N s, "
    f"{counts[Status.CONVERGED]} steps converged, {counts[Status.MAX_ITER]} at the cap"
)
assert bool(mp.docked) and counts[Status.INFEASIBLE] == counts[Status.NONFINITE] == 0

# %% [markdown]
# ## 3. Sixteen disturbed maneuvers in one call
#
# With `disturbed=True` the loop takes a PRNG key: the guidance sees the state with
# navigation noise, and the thrusters apply (1 + w) times the command, w from the
# Carpenter–Lee Gauss–Markov model. `vmap` over keys flies a Monte Carlo batch.

# %%
noisy = dataclasses.replace(sc.config, disturbed=True)
batch = jax.jit(jax.vmap(lambda k: sc.fly(params, x0, noisy, k)))
keys = jax.random.split(jax.random.key(0), 16)
b_infos, b_m = batch(keys)
effort = np.asarray(b_m.effort_l1_N_s)
print(
    f"{int(np.sum(b_m.docked))}/16 docked; effort {effort.mean():.3f} ± {effort.std():.3f} N s "
    f"(undisturbed {float(m.effort_l1_N_s):.3f}); largest violation "
    f"{float(np.max(b_m.max_violation_m)):.1e} m"
)
assert np.all(np.isfinite(np.asarray(b_infos.u)))

fig, ax = plt.subplots(figsize=(6, 4))
for i in range(16):
    n = int(np.sum(b_infos.active[i]))
    ax.plot(b_infos.x[i, :n, 0], b_infos.x[i, :n, 1], lw=0.8, alpha=0.7)
ax.plot(infos.x[: int(np.sum(infos.active)), 0], infos.x[: int(np.sum(infos.active)), 1], "k")
ax.set_aspect("equal")
ax.set_xlabel("x [m]")
ax.set_ylabel("y [m]")
ax.set_title("16 disturbed runs (colour), undisturbed (black)", fontsize=10)
fig.tight_layout()
fig.savefig("disturbed_runs.png")
