"""The solver comparison of paper 000 Sec. IV: the same closed loop flown with each solver.

For a named scenario: rvdjax Fast MPC (paper mode, Riccati step), the dense ISNM variant
(paper mode, dense KKT solve), rvdjax accurate mode, Clarabel in the same jitted loop
(``SolverSettings(backend="clarabel")``: a host callback per step, any scenario), HPIPM in
the same loop where its library is installed (``backend="hpipm"``, :mod:`rvdjax.peers_hpipm`),
and — when CasADi is installed (``pip install 'rvdjax[nmpc]'``) — a
nonlinear MPC solved by IPOPT with the ellipsoidal keep-out constraints kept nonlinear (paper
000 Eq. 6) for the rendezvous scenarios, and the inverse-dynamics guidance of paper 001
(:mod:`rvdjax.idvd`) for the POSEIDYN scenarios. Each row: the scenario's figures (total impulse /
effort, time to dock, violation) and the mean solve time per MPC step.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import numpy as np

from rvdjax.loop import fly
from rvdjax.peers_hpipm import hpipm_unavailable
from rvdjax.scenarios import FlightOptions, get_scenario
from rvdjax.solver import SolverSettings

__all__ = ["compare_solvers", "VARIANTS", "format_comparison"]

# label -> (settings of a scenario, solver-parameter mode, paper-000 name of the same algorithm)
VARIANTS = {
    "rvdjax Fast MPC (paper mode)": (lambda sc: sc.settings("paper"), "paper", "Fast MPC"),
    "rvdjax ISNM (paper mode, dense)": (
        lambda sc: dataclasses.replace(sc.settings("paper"), method="dense"),
        "paper",
        "ISNM",
    ),
    "rvdjax accurate": (lambda sc: sc.settings("accurate"), "accurate", None),
    "Clarabel in the loop": (lambda sc: SolverSettings(backend="clarabel"), "accurate", None),
    "HPIPM in the loop": (lambda sc: SolverSettings(backend="hpipm"), "accurate", None),
}
_NOTES = {
    "Clarabel in the loop": "host callback per step incl. QP assembly, wall time / step",
    "HPIPM in the loop": "host callback per step incl. QP assembly, wall time / step",
}


def _row(label, m, ms_per_step, published, paper_name, note=""):
    effort = float(m.effort_l1_N_s)
    ref = published.get("effort_l1_N_s", {}).get(paper_name) if paper_name else None
    return {
        "solver": label,
        "docked": bool(m.docked),
        "effort_l1_N_s": effort,
        "time_to_dock_s": float(m.time_to_dock_s) if bool(m.docked) else None,
        "max_violation_m": float(m.max_violation_m),
        "status_counts": [int(c) for c in np.asarray(m.status_counts)],
        "ms_per_step": ms_per_step,
        "paper_effort_l1_N_s": ref,
        "rel_diff_to_paper": (effort - ref) / ref if ref else None,
        "note": note,
    }


def compare_solvers(
    name: str = "fastmpc-3d",
    progress=print,
    nmpc: bool = True,
    thrusters: bool = False,
    warmup: bool = True,
    options: FlightOptions | None = None,
) -> list[dict]:
    """Fly scenario ``name`` with every solver; return one row per solver. ``options``: the
    flight (:class:`~rvdjax.scenarios.flight.FlightOptions`; its mode is each variant's own;
    default: ideal forces, or the thruster set with ``thrusters``): the rvdjax, Clarabel and
    HPIPM loops fly it, the NMPC and IDVD baselines keep their own ideal-force plants and fly only a
    noiseless linear truth. ``warmup``: fly each compiled loop once before the timed flight
    (False: the one flight is timed, first-call costs included)."""
    sc = get_scenario(name)
    options = FlightOptions(thrusters=thrusters) if options is None else options
    thrusters = options.thrusters is not False
    rows = []
    for label, (settings_of, mode, paper_name) in VARIANTS.items():
        if label == "HPIPM in the loop" and (why := hpipm_unavailable()):
            progress(f"note: HPIPM skipped ({why})")
            continue
        flight = sc.flight(options.replace(mode=mode), settings=settings_of(sc))
        loop, params, x0, sp = flight.loop, flight.params, flight.x0, flight.solver_params
        key = flight.key if options.disturbed else None
        run = jax.jit(lambda p, x, k, s, lp=loop: fly(lp, p, x, k, s))
        run = run.lower(params, x0, key, sp).compile()
        if warmup:
            jax.block_until_ready(run(params, x0, key, sp))
        t0 = time.perf_counter()
        infos, m = jax.block_until_ready(run(params, x0, key, sp))
        steps = max(int(np.sum(np.asarray(infos.active))), 1)
        ms = 1e3 * (time.perf_counter() - t0) / steps
        note = _NOTES.get(label, "jitted closed loop, wall time / step")
        rows.append(_row(label, m, ms, sc.published, paper_name, note=note))
        progress(f"{label}: effort {float(m.effort_l1_N_s):.6g} N s, {ms:.3f} ms/step")

    if options.disturbed or options.truth != "linear":
        progress("note: the NMPC and IDVD baselines fly the noiseless linear truth only: skipped")
        nmpc = False
    baselines = sc.guidance_family.baselines if nmpc else ()
    if "nmpc" in baselines:
        try:
            from rvdjax.nmpc import run_nmpc_loop
        except ImportError as err:
            progress(f"note: NMPC skipped ({err}); pip install 'rvdjax[nmpc]'")
        else:
            ideal = sc.flight(options.replace(mode="accurate", thrusters=False))
            infos, m, solve_s = run_nmpc_loop(ideal.params, ideal.x0, ideal.loop)
            steps = max(int(np.sum(infos["active"])), 1)
            rows.append(
                _row(
                    "NMPC (CasADi + IPOPT)",
                    m,
                    1e3 * solve_s / steps,
                    sc.published,
                    "IPOPT NMPC",
                    note="nonlinear keep-out constraints, solver calls only"
                    + (", ideal forces" if thrusters else ""),
                )
            )
            progress(f"NMPC: effort {float(m.effort_l1_N_s):.6g} N s")

    if "idvd" in baselines:
        # paper 001 Sec. 3.2: inverse dynamics in the virtual domain, planned with IPOPT
        try:
            from rvdjax.idvd import run_idvd
        except ImportError as err:
            progress(f"note: IDVD skipped ({err}); pip install 'rvdjax[nmpc]'")
        else:
            # the paper's flight: re-planned at 5 Hz, <= 15 warm-started IPOPT iterations
            res = run_idvd(
                "retuned" if name.endswith("retuned") else "initial",
                replan_period_s=0.2,
                replan_max_iter=15,
            )
            ref = res["published"]["effort_l1_N_s"]
            rows.append(
                {
                    "solver": "IDVD (CasADi + IPOPT)",
                    "docked": res["docked"],
                    "effort_l1_N_s": res["effort_l1_N_s"],
                    "time_to_dock_s": res["time_to_dock_s"] if res["docked"] else None,
                    "max_violation_m": res["max_violation_m"],
                    "status_counts": None,
                    "ms_per_step": 1e3 * res["solve_time_s"] / res["n_solves"],
                    "paper_effort_l1_N_s": ref,
                    "rel_diff_to_paper": (res["effort_l1_N_s"] - ref) / ref,
                    "note": f"re-planned at 5 Hz ({res['n_solves']} IPOPT solves, "
                    f"{res['mean_replan_iterations']:.1f} iterations each); ms per solve; "
                    f"paper IDVD time {res['published']['time_to_dock_s']} s",
                }
            )
            progress(f"IDVD: effort {res['effort_l1_N_s']:.4g} N s")
    return rows


def format_comparison(name: str, rows: list[dict], published: dict) -> str:
    lines = [f"{name}: the same closed loop with each solver"]
    lines.append(
        f"{'solver':<34}{'docked':>7}{'effort N s':>12}{'t dock s':>10}"
        f"{'viol m':>9}{'ms/step':>9}{'paper':>10}{'diff':>8}"
    )
    for r in rows:
        ref = r["paper_effort_l1_N_s"]
        lines.append(
            f"{r['solver']:<34}{str(r['docked']):>7}{r['effort_l1_N_s']:>12.5g}"
            f"{(r['time_to_dock_s'] or float('nan')):>10.1f}{r['max_violation_m']:>9.1e}"
            f"{r['ms_per_step']:>9.3f}{(ref if ref else float('nan')):>10.5g}"
            + (f"{100 * r['rel_diff_to_paper']:>+7.1f}%" if ref else f"{'':>8}")
        )
    for key, refs in published.items():
        lines.append(f"paper's {key}: " + ", ".join(f"{k} {v:g}" for k, v in refs.items()))
    return "\n".join(lines)
