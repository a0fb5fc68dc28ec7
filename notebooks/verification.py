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
# # Verifying a guidance law: worst cases and failure probabilities
#
# A Monte Carlo study answers "how often does it work?" from the runs it happens to draw.
# `rvdjax.verify` asks two sharper questions of a requirement under a dispersion:
#
# 1. **What is the worst case?** Gradient descent on a smooth version of the requirement's
#    margin, through the whole closed loop, against random sampling, a Latin hypercube and
#    CMA-ES at the same budget of closed-loop evaluations.
# 2. **How likely is a failure?** Subset simulation and importance sampling, against crude
#    Monte Carlo, for probabilities Monte Carlo cannot resolve in its budget.
#
# A requirement is a signed margin of one run (>= 0: satisfied), e.g. the clearance of the
# keep-out zone over the whole truth trajectory, at the samples and between them; a dispersion
# is one standard-normal vector xi that sets the run's inputs (here offsets of the initial
# state: 5 cm and 5 mm/s per axis). The case is paper 001's POSEIDYN approach past an obstacle
# (`poseidyn-lqmpc`), small so that the tests can run the notebook; the benchmark
# (`sweeps/verification_benchmark.py`) runs paper 003's `thesis-vbar` under its
# initial-condition distribution at full size.

# %%
import os
import tempfile

import matplotlib.pyplot as plt
import numpy as np

from rvdjax.provenance import ProvenanceError, format_provenance
from rvdjax.verify import ProbabilitySpec, ProblemSpec, SearchSpec, estimate, problem_for, search
from rvdjax.verify.store import EvalStore

BUDGET = int(os.environ.get("RVDJAX_VERIFY_BUDGET", "6"))
REPEATS = int(os.environ.get("RVDJAX_VERIFY_REPEATS", "2"))

# %% [markdown]
# ## The problem: 10 cm of clearance from the obstacle under initial-state offsets
#
# `keep-out>=0.1`: the margin is the clearance of the keep-out circle minus 0.1 m.

# %%
pb = problem_for(ProblemSpec("poseidyn-lqmpc", "keep-out>=0.1", "x0:0.05,0.005", n_steps=60))
for note in pb.notes():
    print("-", note)

# %% [markdown]
# ## Worst-case search
#
# Every method gets the same budget of forward evaluations per repeat; a gradient evaluation
# is counted at its measured cost in forward evaluations (the same runs flown forward the
# same way). Each gradient iteration judges a line search along the smooth margin's descent
# direction (here 2 steps, in standard deviations) and the HL-RF point by the exact margin.

# %%
spec = SearchSpec(methods=("gradient", "random", "cma-es"), budget=BUDGET, repeats=REPEATS,
                  popsize=2, starts=1, ladder=2)  # fmt: skip
traces = search(pb, spec, progress=False)
for method, tr in traces.items():
    s = tr.summary()
    print(f"{method:<10} falsified {s['falsification_rate']:.0%}  worst margin "
          f"{s['worst_margin']:.3g} m  ({s['wall_s']:.1f} s)")  # fmt: skip

# %%
fig, ax = plt.subplots(figsize=(6, 3.5))
for method, tr in traces.items():
    for ev, best in zip(tr.evals, tr.best, strict=True):
        ax.step(ev, best, where="post", color={"gradient": "C0", "random": "C1"}.get(method, "C2"))
    ax.plot([], [], color={"gradient": "C0", "random": "C1"}.get(method, "C2"), label=method)
ax.axhline(0, color="k", lw=0.8, ls="--")
ax.set_xlabel("forward evaluations")
ax.set_ylabel("best keep-out margin found [m]")
ax.legend()
plt.show()

# %% [markdown]
# ## Failure probability
#
# The probability that the clearance falls below 10 cm, by subset simulation: two
# independent replicates of 50 runs a level (`RVDJAX_VERIFY_BUDGET=100`: 2000 runs), whose
# spread gives the CoV.

# %%
spec = ProbabilitySpec("subset", max(200, 20 * BUDGET), level_size=50, replicates=2)
res = estimate(pb, spec, None, False)
print(f"p = {res['p']:.3g}, CoV {res['cov']}, 95 % interval {np.round(res['ci95'], 5)}, "
      f"{res['runs']} runs")  # fmt: skip

# %% [markdown]
# ## Provenance
#
# A verification directory records which code, on which machine, flew which runs: the
# package's source hash, git commit, jax/jaxlib versions and device, and a hash of everything
# that defines a run (scenario values, parameters, loop, solver, requirement, dispersion).
# Reusing its evaluations for another definition stops with one line naming what differs.

# %%
directory = tempfile.mkdtemp()
store = EvalStore(directory, pb.effort_key, {"problem": pb.definition()})
for line in format_provenance(store.block):
    print(line)
other = problem_for(ProblemSpec("poseidyn-lqmpc", "keep-out>=0.2", "x0:0.05,0.005", n_steps=60))
try:
    EvalStore(directory, other.effort_key, {"problem": other.definition()})
except ProvenanceError as err:
    print(err)
