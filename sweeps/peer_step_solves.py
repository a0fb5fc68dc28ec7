"""The host solvers of the study benchmark on the same MPC-step QPs, one solve at a time:
Clarabel, PIQP, DAQP on the sparse form, and DAQP on the condensed form (rvdjax.qp.condense),
cold and warm-started with its own optimal active set (a bound on what any warm start from
the previous MPC step could give). The QPs are the first MPC step of ``--runs`` runs of
paper 003 Sec. 4.1's initial conditions (as ``sweeps/study_benchmark.py`` flies them).

    taskset -c 0 python sweeps/peer_step_solves.py [--scenario thesis-vbar] [--runs 8]

Prints milliseconds per QP (mean over the QPs of the best of 5 solves) and the largest
objective difference from Clarabel's reference solve.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import rvdjax  # noqa: F401  (float64, XLA options)


def _best_ms(fn, repeats: int = 5) -> float:
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return 1e3 * best


def _cases(qp):
    """name -> (solve, z or None) for one QP (z given where the call does not return it)."""
    import daqp

    from rvdjax import peers
    from rvdjax.qp import condense

    c = condense(qp)
    data = peers.daqp_condensed_data(c)
    _, _, _, info = daqp.solve(*data)
    active = (np.abs(np.asarray(info["lam"])) > 0).astype(np.int32)

    def warm():
        return daqp.solve(*data, active.copy())

    return c, {
        "Clarabel (sparse)": (lambda: peers.solve_clarabel(qp, mode="benchmark"), None),
        "PIQP (sparse)": (lambda: peers.solve_piqp(qp), None),
        "DAQP (sparse form)": (lambda: peers.solve_daqp(qp), None),
        "condensing alone": (lambda: condense(qp), None),
        "DAQP condensed, cold (incl. condensing)": (lambda: peers.solve_daqp_condensed(qp), None),
        "DAQP condensed, own active set (solve only)": (
            warm,
            c.Z @ np.asarray(warm()[0]) + c.z0,
        ),
    }


def main(argv=None) -> None:
    import jax

    from rvdjax import peers
    from rvdjax.loop.kernel import init, prepare
    from rvdjax.qp import qp_objective, to_qp
    from rvdjax.scenarios import FlightOptions, get_scenario
    from rvdjax.study import StudySpec
    from rvdjax.study.runner import run_inputs

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="thesis-vbar")
    ap.add_argument("--runs", type=int, default=8)
    args = ap.parse_args(argv)
    sc = get_scenario(args.scenario)
    flight = sc.flight(FlightOptions())
    params, _, loop = flight.params, flight.x0, flight.loop
    spec = StudySpec(kind="montecarlo", scenario=sc.name, n_initial=args.runs, initial="paper003")
    rs = run_inputs(spec, sc, np.arange(args.runs))
    rows: dict[str, list] = {}
    for i in range(args.runs):
        st = init(loop, params, rs.x0[i], rs.keys[i])
        qp = to_qp(jax.tree.map(np.asarray, prepare(loop, params, st).ocp), soft=True)
        ref = peers.solve_clarabel(qp)
        c, cases = _cases(qp)
        for name, (fn, z) in cases.items():
            ms = _best_ms(fn)
            out = fn()
            if z is None and hasattr(out, "z"):
                z = out.z
            err = np.nan if z is None else abs(qp_objective(qp, z) - ref.objective)
            err /= 1.0 + abs(ref.objective)  # NaN for the condensing alone
            rows.setdefault(name, []).append((ms, err))
        print(f"run {i}: {c.H.shape[0]} condensed variables, {c.G.shape[0]} general rows")
    print(f"\n{'solver':<46}{'ms / QP':>9}{'max rel. objective diff':>26}")
    for name, v in rows.items():
        a = np.asarray(v)
        print(f"{name:<46}{a[:, 0].mean():>9.2f}{np.max(a[:, 1]):>26.1e}")


if __name__ == "__main__":
    main()
