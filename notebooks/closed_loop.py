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
# 3. fly 16 disturbed copies through the batch engine (navigation noise and the Gauss–Markov
#    thrust error of paper 003 Ch. 5, one PRNG key each) and look at the spread.
#
# Run it with `python notebooks/closed_loop.py` (about a minute, most of it compilation).

# %%
import tempfile
from pathlib import Path

import jax
import matplotlib.pyplot as plt
import numpy as np

import rvdjax  # noqa: F401  (enables float64 in JAX)
from rvdjax.loop import fly
from rvdjax.loop.engine import EngineConfig, fly_batch
from rvdjax.scenarios import get_scenario
from rvdjax.solver import Status

sc = get_scenario("rotating-target-b")
params, x0 = sc.build()  # physical values -> checked traced parameters (once)
print(sc.description, f"[{sc.source}; family {sc.family}]")

# %% [markdown]
# ## 1. One maneuver
#
# `sc.loop()` is the static closed loop (the family's functions and the configuration);
# `fly(loop, params, x0)` is the whole maneuver as one `lax.scan` of the kernel's `step`: a
# pure function of arrays, so `jax.jit` compiles it once.

# %%
loop = sc.loop()
infos, m = jax.jit(lambda p, x: fly(loop, p, x))(params, x0)
print(
    f"docked {bool(m.docked)} after {float(m.time_to_dock_s):.0f} s, "
    f"effort {float(m.effort_l1_N_s):.3f} N s, largest violation "
    f"{float(m.max_violation_m):.1e} m, statuses {np.asarray(m.status_counts)}"
)
assert bool(m.docked) and float(m.max_violation_m) == 0.0
OUT = Path(tempfile.mkdtemp(prefix="rvdjax-closed-loop-"))  # the figures' files
sc.guidance_family.plot(OUT / "rotating_target_b.png", sc, params, infos)  # path, thrust, r_hold
fig, ax = plt.subplots(figsize=(9, 6))
ax.imshow(plt.imread(OUT / "rotating_target_b.png"))
ax.set_axis_off()
plt.show()

# %% [markdown]
# ## 2. Paper mode
#
# Paper 000's Algorithm 1: a fixed barrier weight kappa and at most 10 Newton steps per MPC
# step. kappa is a traced solver parameter: `sc.solver_params("paper")` carries the scenario's
# value (here 6.25e-3: with 0.05 the barrier holds the chaser ~0.1 m off the port).

# %%
paper = sc.loop("paper")
_, mp = jax.jit(lambda p, x, s: fly(paper, p, x, None, s))(params, x0, sc.solver_params("paper"))
counts = np.asarray(mp.status_counts)
print(
    f"paper mode (kappa {sc.paper_kappa:g}): docked {bool(mp.docked)} after "
    f"{float(mp.time_to_dock_s):.0f} s, effort {float(mp.effort_l1_N_s):.3f} N s, "
    f"{counts[Status.CONVERGED]} steps converged, {counts[Status.MAX_ITER]} at the cap"
)
assert bool(mp.docked) and counts[Status.INFEASIBLE] == counts[Status.NONFINITE] == 0

# %% [markdown]
# ## 3. Sixteen disturbed maneuvers through the batch engine
#
# With `disturbed=True` each run draws navigation noise and thrust errors from its own PRNG
# key. The batch engine flies the queue of runs through a fixed set of slots: a slot whose run
# has docked takes the next run, and a solve that needs more iterations continues on the
# next tick, so no run waits for the slowest one.

# %%
noisy = sc.loop(disturbed=True)
keys = jax.random.split(jax.random.key(0), 16)
b_m = fly_batch(noisy, params, np.repeat(x0[None], 16, 0), keys, config=EngineConfig(slots=8))
effort = np.asarray(b_m.effort_l1_N_s)
print(
    f"{int(np.sum(b_m.docked))}/16 docked; effort {effort.mean():.3f} ± {effort.std():.3f} N s "
    f"(undisturbed {float(m.effort_l1_N_s):.3f}); largest violation "
    f"{float(np.max(b_m.max_violation_m)):.1e} m"
)
assert np.all(np.isfinite(effort))

# the trajectories of a few of them, flown one at a time for the record of every step
run = jax.jit(lambda k: fly(noisy, params, x0, k)[0])
fig, ax = plt.subplots(figsize=(6, 4))
for k in keys[:6]:
    x = run(k).x
    ax.plot(x[:, 0], x[:, 1], lw=0.8, alpha=0.7)
ax.plot(infos.x[: int(np.sum(infos.active)), 0], infos.x[: int(np.sum(infos.active)), 1], "k")
ax.set_aspect("equal")
ax.set_xlabel("x [m]")
ax.set_ylabel("y [m]")
ax.set_title("disturbed runs (colour), undisturbed (black)", fontsize=10)
fig.tight_layout()
fig.savefig(OUT / "disturbed_runs.png")
plt.show()
