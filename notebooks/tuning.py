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
# # Tuning MPC weights by gradient through the closed loop
#
# `rvdjax.tune` differentiates whole closed-loop maneuvers (every MPC solve by its implicit
# derivative) and lets Adam change a scenario's weights. Here:
#
# 1. tune the weights Q, R and the terminal scale of `poseidyn-lqmpc` (paper 001, the initial
#    tuning) from their hand values, against a random search with the same number of
#    closed-loop evaluations, and judge all three on held-out maneuvers,
# 2. look at the training loss, the held-out distributions and one maneuver before and after,
# 3. trace a trade-off curve between effort and time to dock by changing the loss's weights.
#
# **The loss.** Docking time and the docked flag are piecewise constant in the weights (zero
# derivative almost everywhere), so the tuner minimises a smooth surrogate per maneuver,
#
# $$L = w_e\,E/E_\mathrm{ref} + w_t\,T/T_\mathrm{ref} + w_m\,M,$$
#
# with E the headline effort (smoothed norms), T a soft time to dock (each step's duration
# weighted by log(1 + d/d0), d the distance to the port: it keeps adding until the run docks)
# and M a squared penalty on truth constraint violations. E_ref and T_ref are the hand tuning's
# training means, so L = w_e + w_t at the start. **Results are judged with the exact metrics**
# (effort, time to dock, docked fraction, largest violation) on maneuvers never trained on.
#
# The sizes here are small so that the test suite can run the notebook; set
# `RVDJAX_TUNE_TRAIN`, `RVDJAX_TUNE_STEPS` and `RVDJAX_TUNE_HELDOUT` (e.g. 16 / 30 / 64) to run
# it at full size (then the trade-off curve also gets more points; `RVDJAX_TUNE_WEIGHTS`, e.g.
# `0.5,1,2`, sets its time weights). The closed loop and its gradient compile once (the loss
# weights are traced), which is most of this notebook's run time.

# %%
import os
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import pandas as pd

import rvdjax  # noqa: F401  (enables float64 in JAX)
from rvdjax.tune import TuneSpec, parse_loss, tune
from rvdjax.tune.figures import plot_heldout, plot_loss_history, plot_tradeoff

SMALL = {"train": 4, "steps": 3, "heldout": 4}
SIZE = {k: int(os.environ.get(f"RVDJAX_TUNE_{k.upper()}", v)) for k, v in SMALL.items()}
FULL = SIZE != SMALL
TIME_WEIGHTS = (0.25, 0.5, 1.0, 2.0, 4.0) if FULL else (0.5, 2.0)
if os.environ.get("RVDJAX_TUNE_WEIGHTS"):  # e.g. "0.5,1,2": the trade-off's time weights
    TIME_WEIGHTS = tuple(float(w) for w in os.environ["RVDJAX_TUNE_WEIGHTS"].split(","))
OUT = Path(tempfile.mkdtemp(prefix="rvdjax-tune-"))
print(SIZE, "time weights of the trade-off:", TIME_WEIGHTS)


def spec_for(time_weight: float = 1.0, random_search: bool = True) -> TuneSpec:
    return TuneSpec(
        scenario="poseidyn-lqmpc",
        params=("Q", "R", "terminal_scale"),
        loss=parse_loss(f"effort=1,time={time_weight:g}"),
        n_steps=45,
        lr=0.03,
        random_search=random_search,
        **SIZE,
    )


# %% [markdown]
# ## 1. Tune, and judge on held-out maneuvers
#
# The training and held-out sets are the scenario's initial state with each position component
# multiplied by N(1, 0.05), drawn with different seeds. The returned tuning is the best point
# met on the training loss (by Adam for "tuned", by the random search for "random_search"):
# when no step beats the hand values on the training set, the hand values come back.

# %%
result = tune(spec_for(), out=OUT / "time_1", progress=False)
table = pd.DataFrame(result["heldout"]).T[
    ["effort", "time_to_dock_s", "docked_fraction", "max_violation_m", "loss"]
]
EFFORT = result["heldout"]["hand"]["effort_metric"]
print(f"held out: {result['heldout_runs']} maneuvers; effort = mean {EFFORT}")
print(table.to_string(float_format=lambda v: f"{v:.4g}"))
print("training loss:", {k: round(v, 4) for k, v in result["train_loss"].items()})

# %% [markdown]
# The tuned values against the hand values (Q: the diagonal of the state weight, R: the input
# weight, terminal_scale: the factor on the DARE terminal weight):

# %%
for name, hand in result["values"]["hand"].items():
    print(f"{name:15s} hand {hand}\n{'':15s} tuned {result['values']['tuned'][name]}")

# %% [markdown]
# ## 2. Training loss, held-out distributions, one maneuver before and after
#
# The loss per closed-loop evaluation of the training set (thin: each evaluation, bold: the
# best so far); a gradient evaluation also runs the backward pass.

# %%
history = pd.read_parquet(OUT / "time_1" / "history.parquet").to_dict("records")
fig, ax = plt.subplots(figsize=(6.4, 4.0))
plot_loss_history(ax, history)
plt.show()

# %% [markdown]
# Held-out effort and time to dock per tuning (exact metrics; time to dock of docked runs only,
# their count under each label).

# %%
rows = pd.read_parquet(OUT / "time_1" / "heldout.parquet").to_dict("records")
fig, axes = plt.subplots(1, 2, figsize=(10.0, 4.0))
plot_heldout(axes, rows, EFFORT)
plt.show()

# %% [markdown]
# `tune` also wrote its figures to `OUT/plots`; the first held-out maneuver flown with the hand
# and the tuned values:

# %%
print(sorted(p.name for p in (OUT / "time_1" / "plots").glob("*.png")))
fig, ax = plt.subplots(figsize=(6.4, 5.2))
ax.imshow(plt.imread(OUT / "time_1" / "plots" / "trajectories.png"))
ax.axis("off")
plt.show()

# %% [markdown]
# ## 3. A trade-off curve
#
# The time weight w_t of the loss sets how much a second of docking time is worth against a
# unit of effort. Tuning again for a few w_t (effort weight 1) gives a curve of held-out
# (time to dock, effort) points. A tuned point **dominates** the hand tuning when it lies on
# or below and left of the star: lower effort at no later docking (or earlier docking at no
# more effort), on maneuvers it was not tuned on. The held-out set is the same for every
# point (same seed), so the points compare like with like.

# %%
points = [
    {
        "label": "w_t=1",
        "effort": result["heldout"]["tuned"]["effort"],
        "time_to_dock_s": result["heldout"]["tuned"]["time_to_dock_s"],
    }
]
for w in TIME_WEIGHTS:
    if w == 1.0:  # already tuned above
        continue
    r = tune(spec_for(w, random_search=False), progress=False)
    ho = r["heldout"]["tuned"]
    points.append(
        {"label": f"w_t={w:g}", "effort": ho["effort"], "time_to_dock_s": ho["time_to_dock_s"]}
    )
hand = {"label": "hand", **{k: result["heldout"]["hand"][k] for k in ("effort", "time_to_dock_s")}}
print(pd.DataFrame([hand, *points]).to_string(index=False, float_format=lambda v: f"{v:.4g}"))
dominating = [
    p["label"]
    for p in points
    if None not in (p["effort"], p["time_to_dock_s"], hand["effort"], hand["time_to_dock_s"])
    and p["effort"] <= hand["effort"]
    and p["time_to_dock_s"] <= hand["time_to_dock_s"]
    and (p["effort"], p["time_to_dock_s"]) != (hand["effort"], hand["time_to_dock_s"])
]
print("tunings that dominate the hand tuning:", dominating or "none")

fig, ax = plt.subplots(figsize=(6.4, 4.4))
plot_tradeoff(ax, points, hand)
ax.set_ylabel(f"mean {EFFORT}, held out")
plt.show()
