"""A study's summary from its table: success bounds, percentiles, worst runs, per-point rows."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rvdjax import provenance
from rvdjax.study import stats
from rvdjax.study.spec import StudySpec
from rvdjax.study.table import read_config, read_table, table_columns

__all__ = ["summarize", "format_summary", "replay_command"]

# A run fails when it does not dock or its truth violates a hard constraint (> 1 um).
VIOLATION_TOL_M = 1e-6


def replay_command(spec: StudySpec, out, run: int) -> str:
    return f"rvdjax run {spec.scenario} --study {out} --run {run}"


def _moments(values) -> dict:
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if not v.size:
        return {"mean": None, "std": None, **stats.percentiles(v)}
    return {
        "mean": float(v.mean()),
        "std": float(v.std(ddof=1)) if v.size > 1 else 0.0,
        **stats.percentiles(v),
    }


def _success(df):
    return df["docked"].to_numpy() & (df["max_violation_m"].to_numpy() <= VIOLATION_TOL_M)


def _block(df, confidence: float) -> dict:
    ok = _success(df)
    n, k = len(df), int(ok.sum())
    docked = df[df["docked"]]
    margins = {
        c[len("margin_") : -len("_m")]: float(df[c].min())
        for c in df.columns
        if c.startswith("margin_")
    }
    return {
        "runs": n,
        "docked": int(df["docked"].sum()),
        "successes": k,
        "failures": n - k,
        "docked_fraction": float(df["docked"].mean()) if n else 0.0,
        "success_fraction": k / n if n else 0.0,
        "success_lower_bound": stats.clopper_pearson_lower(k, n, confidence),
        "effort": _moments(docked["effort"]),
        "delta_v_m_s": _moments(docked["delta_v_m_s"]),
        "time_to_dock_s": _moments(docked["time_to_dock_s"]),
        "max_violation_m": {
            "max": float(df["max_violation_m"].max()) if n else None,
            **stats.percentiles(df["max_violation_m"]),
        },
        "smallest_margin_m": margins,
    }


def summarize(out, confidence: float = 0.9, reliability: float = 0.9973, worst: int = 5) -> dict:
    """The summary of the study in ``out`` (JSON-ready)."""
    out = Path(out)
    config = read_config(out)
    if config is None:
        raise ValueError(f"{out}: no config.json (not a study directory)")
    spec = StudySpec.from_dict(config["spec"])
    # the columns the statistics and the provenance counts need (a 10^6-run study's other
    # strings stay on disk)
    names = table_columns(out)
    wanted = ["point", "docked", "max_violation_m", "effort", "delta_v_m_s", "time_to_dock_s"]
    wanted += [c for c in names if c.startswith("margin_")]
    wanted += [c for c in ("provenance", "code_changed") if c in names]
    df = read_table(out, columns=wanted)
    from rvdjax.study.runner import effort_metric
    from rvdjax.study.spec import study_scenario

    sc = study_scenario(spec, out)
    summary = {
        "study": spec.kind,
        "scenario": spec.scenario,
        "effort_metric": effort_metric(sc),
        "runs_planned": spec.n_runs,
        "complete": len(df) == spec.n_runs,
        "confidence": confidence,
        **_block(df, confidence),
        "reliability_target": reliability,
        "zero_failure_runs_needed": stats.zero_failure_runs(reliability, confidence),
    }
    summary["assumptions"] = study_notes(spec)
    summary["provenance"] = provenance.summary(config.get("provenance"), df)  # provenance hook
    ok = _success(df)
    if ok.all():
        summary["reliability_shown"] = stats.demonstrated_reliability(len(df), confidence)
    # worst runs: every failure first, then the largest efforts
    bad = df[~ok]
    good = df[ok].sort_values("effort", ascending=False)
    pick = [*bad["run"].tolist(), *good["run"].tolist()][:worst]
    rows = read_table(out, columns=["point", "status", "failure", "effort", "time_to_dock_s"],
                      runs=pick).set_index("run").loc[pick]  # fmt: skip
    summary["worst_runs"] = [
        {
            "run": int(r),
            "point": int(rows.loc[r, "point"]),
            "status": str(rows.loc[r, "status"]),
            "failure": str(rows.loc[r, "failure"]),
            "effort": float(rows.loc[r, "effort"]),
            "time_to_dock_s": float(rows.loc[r, "time_to_dock_s"]),
            "replay": replay_command(spec, out, int(r)),
        }
        for r in pick
    ]
    if len(spec.points) > 1:
        summary["points"] = []
        for p in spec.points:
            sub = df[df["point"] == p.index]
            if len(sub):
                summary["points"].append({"point": p.index, **p.values, **_block(sub, confidence)})
    return summary


def study_notes(spec: StudySpec) -> list[str]:
    """What the study assumed beyond its scenario (printed with every summary)."""
    notes = [
        f"success = docked with no hard-constraint violation by the truth above "
        f"{VIOLATION_TOL_M:g} m; bounds one-sided Clopper-Pearson; percentiles over docked runs",
    ]
    if spec.initial == "paper003":
        notes.append(
            "initial states (paper 003 Sec. 4): range U(0.15, 2.5) km, bearing uniform in the "
            "orbital plane and z = 0 (the thesis gives no direction law), velocity (0, -2 n x, "
            "0) + N(0, 0.5 m/s) per axis"
        )
    if spec.disturbed:
        notes.append(
            "disturbed: navigation noise, Gauss-Markov thrust error and minimum impulse bit of "
            "the scenario (paper 003 Ch. 5); "
            + ("Kalman navigation filter (rvdjax's choice)" if spec.nav_filter else "no filter")
        )
    if spec.time_limit_s is not None:
        notes.append(f"a run not docked within {spec.time_limit_s:g} s fails (TIMEOUT)")
    if spec.thrusters:
        from rvdjax.scenarios import get_scenario

        sc = get_scenario(spec.scenario)
        notes.append(f"thrusters: {sc.thrusters.describe()}")
        notes.extend(sc.thrusters.assumptions)
        for i, kind, t in spec.faults:
            known = "known to the allocation (FDIR)" if spec.fdir else "unnoticed"
            notes.append(f"thruster {i} {kind} from t = {t:g} s in every run, {known}")
    return notes


def _f(v, fmt="{:.4g}"):
    return "-" if v is None else fmt.format(v)


def format_summary(s: dict) -> str:
    e, t = s["effort"], s["time_to_dock_s"]
    lines = [
        f"{s['study']} {s['scenario']}: {s['runs']} runs"
        + ("" if s["complete"] else f" of {s['runs_planned']} (incomplete)"),
        f"  docked {s['docked']} / {s['runs']}; successes (docked, no violation) "
        f"{s['successes']}; P(success) >= {s['success_lower_bound']:.4f} at "
        f"{100 * s['confidence']:g} % (one-sided Clopper-Pearson)",
        f"  {s['zero_failure_runs_needed']} zero-failure runs show "
        f"{100 * s['reliability_target']:g} % at {100 * s['confidence']:g} % confidence",
        f"  {s['effort_metric']:<18} mean {_f(e['mean'])}  std {_f(e['std'])}  p50 "
        f"{_f(e['p50'])}  p95 {_f(e['p95'])}  p99.73 {_f(e['p99.73'])}",
        f"  {'time_to_dock_s':<18} mean {_f(t['mean'])}  std {_f(t['std'])}  p50 "
        f"{_f(t['p50'])}  p95 {_f(t['p95'])}  p99.73 {_f(t['p99.73'])}",
        f"  largest violation {_f(s['max_violation_m']['max'])} m; smallest margins "
        + ", ".join(f"{k} {_f(v)} m" for k, v in s["smallest_margin_m"].items()),
    ]
    if "points" in s:
        lines.append("  per sweep point:")
        for p in s["points"]:
            label = ", ".join(
                f"{k}={v:g}" for k, v in p.items() if k not in _BLOCK_KEYS and k != "point"
            )
            lines.append(
                f"    [{p['point']:>3}] {label:<28} failures {p['failures']:>4}/{p['runs']:<5} "
                f"effort {_f(p['effort']['mean'])}  t {_f(p['time_to_dock_s']['mean'])} s"
            )
    lines.append("  assumptions:")
    lines.extend(f"    - {a}" for a in s.get("assumptions", []))
    lines.append("  provenance:")  # provenance hook
    lines.extend(f"    - {a}" for a in provenance.summary_lines(s.get("provenance")))
    lines.append("  worst runs:")
    for w in s["worst_runs"]:
        lines.append(
            f"    run {w['run']:>6} {w['status']:<8} effort {_f(w['effort'])}  "
            f"{w['failure'] or 'ok'}  ->  {w['replay']}"
        )
    return "\n".join(lines)


_BLOCK_KEYS = {
    "runs",
    "docked",
    "successes",
    "failures",
    "docked_fraction",
    "success_fraction",
    "success_lower_bound",
    "effort",
    "delta_v_m_s",
    "time_to_dock_s",
    "max_violation_m",
    "smallest_margin_m",
}
