"""A failed thruster against the healthy vehicle: one thruster stuck off from t = 0 in
``spot-2d-a`` and ``rotating-target-b``, over dispersed runs (initial position +-5 cm 1-sigma
per axis, thrust magnitude 3 % 1-sigma and misalignment 0.01 rad 1-sigma per thruster), the
allocation aware of the fault (FDIR) or not.

Each configuration is a resumable study (``rvdjax study montecarlo ... --thrusters
[--fault 0:stuck-off] [--no-fdir]``) under ``--out``; the table compares the docked fraction,
the effort (paper 002 Eq. 11: every thruster's impulse), time to dock and the smallest truth
margins.

    python sweeps/failed_thruster.py --out failed-thruster/ [--runs 256]
"""

from __future__ import annotations

import argparse
import os

import numpy as np
import pandas as pd

from rvdjax.scenarios import get_scenario
from rvdjax.study import StudySpec, run_study

SCENARIOS = ("spot-2d-a", "rotating-target-b")
VARY = (
    ("x0[0]", "+normal(0,0.05)"),
    ("x0[1]", "+normal(0,0.05)"),
    ("thruster_magnitude_error", "normal(0,0.03)"),
    ("thruster_misalignment", "normal(0,0.01)"),
)
CASES = {
    "healthy": dict(faults=()),
    "thruster 0 stuck off, FDIR": dict(faults=((0, "stuck-off", 0.0),)),
    "thruster 0 stuck off, unnoticed": dict(faults=((0, "stuck-off", 0.0),), fdir=False),
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="directory of the studies")
    ap.add_argument("--runs", type=int, default=256)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    rows = []
    for name in SCENARIOS:
        sc = get_scenario(name)
        for label, kw in CASES.items():
            spec = StudySpec(
                kind="montecarlo",
                scenario=name,
                n_initial=args.runs,
                seed=args.seed,
                vary=VARY,
                thrusters=True,
                **kw,
            )
            spec.validate(sc)
            d = os.path.join(
                args.out,
                f"{name}-{label.split(',')[0].replace(' ', '-')}"
                + ("" if kw.get("fdir", True) else "-unnoticed"),
            )
            run_study(spec, d, resume=os.path.exists(d), progress=False)
            t = pd.read_parquet(os.path.join(d, "runs"))
            margins = [c for c in t.columns if c.startswith("margin_")]
            docked = t[t.docked]
            rows.append(
                dict(
                    scenario=name,
                    case=label,
                    runs=len(t),
                    docked=f"{int(t.docked.sum())}/{len(t)}",
                    effort_mean=docked.thruster_impulse_N_s.mean(),
                    effort_p95=np.percentile(docked.thruster_impulse_N_s, 95)
                    if len(docked)
                    else np.nan,
                    force_l1_mean=docked.effort_l1_N_s.mean(),
                    time_mean=docked.time_to_dock_s.mean(),
                    time_p95=np.percentile(docked.time_to_dock_s, 95) if len(docked) else np.nan,
                    max_violation_mm=1e3 * t.max_violation_m.max(),
                    **{m[7:-2] + "_min_mm": 1e3 * t[m].min() for m in margins},
                )
            )
    table = pd.DataFrame(rows)
    with pd.option_context("display.width", 200, "display.max_columns", 30):
        print(table.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
