"""Sensitivity of the thesis cases (paper 003 Tables 3.3-3.5) to the two values the thesis
does not publish: the approach-to-docking switch radius r2 and the docking speed bound v_max.

One batch of 3 cases x 3 radii x 3 speed bounds through the batch engine, each run with its
own parameters (accurate mode, CW truth). Prints a table of delta-v and time to dock relative
to the thesis and the per-phase durations, and writes one row per run to
``thesis_sensitivity.csv`` (or the path given as the argument).

    python sweeps/thesis_sensitivity.py [out.csv]
"""

from __future__ import annotations

import csv
import itertools
import sys

import jax
import numpy as np

from rvdjax.loop.engine import EngineConfig, arrays_source, run_batch
from rvdjax.scenarios import SCENARIOS, FlightOptions
from rvdjax.scenarios.paper003 import CASES as THESIS_CASES

CASES = ("vbar", "rbar", "rotating")
R2 = (10.0, 20.0, 30.0)  # m (rvdjax default 10 m)
V_MAX = (0.1, 0.05, 0.02)  # m/s (rvdjax default 0.1 m/s)


def main(out: str = "thesis_sensitivity.csv") -> int:
    from rvdjax.outputs import check_file

    check_file(out, "out", (".csv",))
    grid = list(itertools.product(CASES, R2, V_MAX))
    # each run's parameters are built and checked from the scenario record with two values
    # changed (r2 < r1 and the speed bound are checked by the family)
    options = FlightOptions(n_steps=400)
    built = [
        SCENARIOS[f"thesis-{c}"].flight(options, check=False, r2=r2, v_max=v) for c, r2, v in grid
    ]
    params = jax.tree.map(lambda *a: np.stack(a), *[b.params for b in built])
    x0 = np.stack([b.x0 for b in built])
    loop = SCENARIOS["thesis-vbar"].flight(options).loop
    result = run_batch(
        loop, arrays_source(x0, params=params), len(grid), config=EngineConfig(slots=16, chunk=8)
    )
    m = result["metrics"]
    rows = []
    for i, (case, r2, v_max) in enumerate(grid):
        _, _, dv, tf, _, phase_t = THESIS_CASES[case]
        rows.append(
            dict(
                case=case,
                r2_m=r2,
                v_max_m_s=v_max,
                docked=bool(m.docked[i]),
                delta_v_m_s=float(m.delta_v_m_s[i]),
                delta_v_rel=float(m.delta_v_m_s[i]) / dv - 1.0,
                time_to_dock_s=float(m.time_to_dock_s[i]),
                time_rel=float(m.time_to_dock_s[i]) / tf - 1.0,
                docking_phase_s=float(m.phase_time_s[i][2]),
                thesis_docking_phase_s=phase_t[2],
                max_violation_m=float(m.max_violation_m[i]),
            )
        )
    with open(out, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print(f"{'case':9}{'r2 m':>6}{'v_max':>7}  {'delta-v':>16}  {'time':>16}  docking phase")
    for r in rows:
        print(
            f"{r['case']:9}{r['r2_m']:6.0f}{r['v_max_m_s']:7.2f}  "
            f"{r['delta_v_m_s']:6.2f} ({100 * r['delta_v_rel']:+5.1f} %)  "
            f"{r['time_to_dock_s']:6.0f} ({100 * r['time_rel']:+5.1f} %)  "
            f"{r['docking_phase_s']:5.0f} s (thesis {r['thesis_docking_phase_s']:.0f})"
        )
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
