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
# # A parameter study with rvdjax
#
# 1. run a small sweep (paper 003 Ch. 4 style: a horizon and a sample time on a grid, the same
#    initial conditions at every point) through the batch engine; the table is written as it
#    goes and pandas reads it,
# 2. summarise it: success bound, percentiles, the worst runs and the command that replays each,
# 3. draw the paper's figures from the table.
#
# The study here is small so that the test suite can run the notebook; `STUDY_DIR` may point at
# any finished study instead (e.g. one written by `python sweeps/paper003_studies.py`).

# %%
import os
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt

import rvdjax  # noqa: F401  (enables float64 in JAX)
from rvdjax.study import StudySpec, format_summary, read_table, run_study, summarize
from rvdjax.study.figures import effort_intervals, failures_per_point, scatter_effort_time

STUDY_DIR = os.environ.get("RVDJAX_STUDY_DIR")

# %%
if STUDY_DIR is None:
    STUDY_DIR = Path(tempfile.mkdtemp(prefix="rvdjax-study-")) / "sweep"
    spec = StudySpec(
        kind="sweep",
        scenario="poseidyn-lqmpc",
        n_initial=4,
        grid=(("N", (15, 20)), ("ts", (4.0, 5.0))),
        vary=(("x0[0]", "+normal(0,0.1)"), ("x0[1]", "+normal(0,0.1)")),
        slots=8,
        chunk=4,
    )
    run_study(spec, STUDY_DIR, progress=False)

# %% [markdown]
# One row per run: the sweep point, the run's seed and drawn values, its metrics and status.

# %%
df = read_table(STUDY_DIR)
print(df[["point", "run", "N", "ts", "status", "effort", "time_to_dock_s"]].head(8))

# %%
summary = summarize(STUDY_DIR)
print(format_summary(summary))

# %%
from rvdjax.study.spec import StudySpec as _Spec  # noqa: E402
from rvdjax.study.table import read_config  # noqa: E402

spec = _Spec.from_dict(read_config(STUDY_DIR)["spec"])
figs = Path(tempfile.mkdtemp(prefix="rvdjax-study-figures-"))  # the paper's figures' files
scatter_effort_time(df, spec, figs / "effort_vs_time.png")
effort_intervals(df, spec, figs / "effort_vs_intervals.png")
failures_per_point(df, spec, figs / "failures.png")

fig, ax = plt.subplots()
for p in spec.points:
    sub = df[(df["point"] == p.index) & df["docked"]]
    ax.scatter(sub["time_to_dock_s"], sub["effort"], s=12, label=p.label())
ax.set_xlabel("time to dock [s]")
ax.set_ylabel(summary["effort_metric"])
ax.legend(fontsize=7)
plt.show()
