"""Tune a scenario's weights by gradient through the batched closed loop, against the hand
tuning and a random search with the same budget, judged on held-out maneuvers (DESIGN §7).

Gradients: ``jax.value_and_grad`` of the mean surrogate (:mod:`rvdjax.tune.loss`) over a
``vmap`` of :func:`rvdjax.loop.fly` (one ``lax.scan`` per maneuver, every solve differentiated
by its implicit derivative, the step under ``jax.checkpoint`` so memory stays bounded for
maneuvers of hundreds of steps). Optimiser: optax Adam on the unconstrained theta
(:mod:`rvdjax.tune.parameters`), cosine-decayed step size, global-norm clipping, non-finite
updates skipped. The returned tuning is the best theta met on the training loss (the same
rule as the random search's). Training and held-out sets are study samplers' runs
(:func:`rvdjax.study.run_inputs`) with different seeds, so no held-out maneuver is trained on.
The set-up (spec, sets, compiled loss and gradient) is :mod:`rvdjax.tune.tuner`; this module
runs the optimiser and the search, judges the tunings and writes their files.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from rvdjax.tune.loss import combine
from rvdjax.tune.tuner import (
    DEFAULT_VARY_SD,
    Tuner,
    TuneSpec,
    _run_set,
    heldout_summary,
    tuner_for,
)

__all__ = ["TuneSpec", "Tuner", "tuner_for", "tune", "heldout_summary", "DEFAULT_VARY_SD"]

NOTES = (
    "surrogate loss (rvdjax's choice): w_e E/E_ref + w_t T/T_ref + w_m M; E the headline "
    "effort with smoothed norms, T = sum dt log(1 + d/d0)/log(101) (d the distance to docking, "
    "d0 = 1 % of the initial distance), M = sum (max(0, -margin)/d0)^2 over the hard truth "
    "rows; E_ref, T_ref the hand tuning's training means. Results are judged with the exact "
    "metrics.",
    "the tuned result is the best theta on the training loss met by Adam (gradient) or by "
    "the random search (theta_hand + sigma N(0, I)); both spend the same number of "
    "closed-loop evaluations of the training set (a gradient evaluation also runs the "
    "backward pass)",
)


def _theta_np(theta) -> dict:
    return {k: np.asarray(v) for k, v in theta.items()}


def tune(spec: TuneSpec, out=None, progress: bool = True) -> dict:
    """Run a tuning (module docstring); write its files to ``out`` when given.

    Returns the summary dict (what ``rvdjax tune --json`` prints)."""
    import optax

    from rvdjax.study.runner import peak_rss_mb

    t_start = time.perf_counter()
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
    tuner = tuner_for(spec)
    sc, space = tuner.scenario, tuner.space
    weights = spec.loss.array()
    x_tr, k_tr = _run_set(spec, sc, spec.train, spec.seed)
    x_ho, k_ho = _run_set(spec, sc, spec.heldout, spec.seed + 1)
    theta_hand = space.theta()

    # reference scales: the hand tuning's training means (compiles the forward pass)
    t0 = time.perf_counter()
    (E, T, M), m_hand_tr = jax.block_until_ready(tuner.terms(theta_hand, x_tr, k_tr))
    compile_forward_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(tuner.terms(theta_hand, x_tr, k_tr))
    forward_s = time.perf_counter() - t0
    refs = (jnp.maximum(jnp.mean(E), 1e-12), jnp.maximum(jnp.mean(T), 1e-12))

    history = []
    bar = _bar(spec.steps + 1, f"tune {sc.name} (gradient)", progress)

    # ---------------------------------------------------------------- gradient run
    schedule = optax.cosine_decay_schedule(spec.lr, max(spec.steps, 1), alpha=0.1)
    opt = optax.apply_if_finite(
        optax.chain(optax.clip_by_global_norm(spec.clip), optax.adam(schedule)), 5
    )
    theta = theta_hand
    state = opt.init(theta)
    best = (np.inf, theta_hand)
    grad_times = []
    for k in range(spec.steps + 1):
        t0 = time.perf_counter()
        if k < spec.steps:
            (L, aux), g = jax.block_until_ready(
                tuner.value_and_grad(theta, x_tr, k_tr, refs, weights)
            )
            gnorm = float(optax.tree.norm(g))
        else:  # the last iterate: a forward evaluation
            (E, T, M), m = tuner.terms(theta, x_tr, k_tr)
            Ls = combine(weights, E, T, M, refs[0], refs[1])
            L, aux, gnorm = jnp.mean(Ls), (Ls, E, T, M, m), None
        wall = time.perf_counter() - t0
        if 0 < k < spec.steps:
            grad_times.append(wall)
        L = float(L)
        if np.isfinite(L) and L < best[0]:
            best = (L, theta)
        history.append(_history_row("gradient", k, k + 1, L, best[0], aux, gnorm, wall))
        if k < spec.steps:
            updates, state = opt.update(g, state, theta)
            theta = optax.apply_updates(theta, updates)
        bar.update(1)
        bar.set_postfix(loss=f"{L:.4g}", best=f"{best[0]:.4g}")
    bar.close()
    theta_grad = best[1]
    grad_step_s = float(np.median(grad_times)) if grad_times else None
    if grad_step_s is None and spec.steps >= 1:
        grad_step_s = history[0]["wall_s"]

    # ---------------------------------------------------------------- random search
    theta_rand = None
    if spec.random_search:
        key = jax.random.key(spec.seed + 2)
        bar = _bar(spec.steps + 1, f"tune {sc.name} (random search)", progress)
        best_r = (np.inf, theta_hand)
        leaves, treedef = jax.tree.flatten(theta_hand)
        for k in range(spec.steps + 1):
            if k == 0:
                cand = theta_hand
            else:
                keys = jax.random.split(jax.random.fold_in(key, k), len(leaves))
                cand = jax.tree.unflatten(
                    treedef,
                    [
                        a + spec.search_sigma * jax.random.normal(kk, a.shape, a.dtype)
                        for a, kk in zip(leaves, keys, strict=True)
                    ],
                )
            t0 = time.perf_counter()
            (E, T, M), m = tuner.terms(cand, x_tr, k_tr)
            Ls = combine(weights, E, T, M, refs[0], refs[1])
            L = float(jnp.mean(Ls))
            wall = time.perf_counter() - t0
            if np.isfinite(L) and L < best_r[0]:
                best_r = (L, cand)
            history.append(
                _history_row("random", k, k + 1, L, best_r[0], (Ls, E, T, M, m), None, wall)
            )
            bar.update(1)
            bar.set_postfix(loss=f"{L:.4g}", best=f"{best_r[0]:.4g}")
        bar.close()
        theta_rand = best_r[1]

    # ---------------------------------------------------------------- held-out judgement
    chunk = spec.train
    tunings = {"hand": theta_hand, "tuned": theta_grad}
    if theta_rand is not None:
        tunings["random_search"] = theta_rand
    heldout, rows = {}, []
    plants = ("ideal", "thrusters") if spec.judge_thrusters else ("ideal",)
    for (label, th), plant in ((t, pl) for pl in plants for t in tunings.items()):
        L, m = tuner.losses(th, x_ho, k_ho, refs, weights, chunk, thrusters=plant == "thrusters")
        key = label if plant == "ideal" else f"{label} (thrusters)"
        heldout[key] = heldout_summary(m, tuner.effort_key, L)
        for i in range(spec.heldout):
            rows.append(
                {
                    "tuning": label,
                    "plant": plant,
                    "run": i,
                    "loss": float(L[i]),
                    "status": int(m.status[i]),
                    "docked": bool(m.docked[i]),
                    "effort": float(getattr(m, tuner.effort_key)[i]),
                    "time_to_dock_s": float(m.time_to_dock_s[i]),
                    "max_violation_m": float(m.max_violation_m[i]),
                    **{f"x0_{j}": float(v) for j, v in enumerate(np.asarray(x_ho[i]))},
                }
            )
    values = {
        label: {k: np.asarray(v) for k, v in space.values(th).items()}
        for label, th in tunings.items()
    }
    result = {
        "scenario": sc.name,
        "family": sc.family,
        "params": list(space.names),
        "n_values": space.size,
        "loss": dataclasses.asdict(spec.loss),
        "mode": spec.mode,
        "train": spec.train,
        "heldout_runs": spec.heldout,
        "steps": spec.steps,
        "n_steps": tuner.loop.config.n_steps,
        "evaluations": {
            "gradient": spec.steps + 1,
            "random_search": spec.steps + 1 if spec.random_search else 0,
        },
        "train_loss": {
            "hand": history[0]["loss"],
            "tuned": float(best[0]),
            **({"random_search": float(best_r[0])} if spec.random_search else {}),
        },
        "heldout": heldout,
        "grad_step_s": grad_step_s,
        "forward_s": forward_s,
        "grad_to_forward": None if grad_step_s is None else grad_step_s / forward_s,
        "compile_forward_s": compile_forward_s,
        "remat": spec.remat,
        "peak_memory_mb": peak_rss_mb(),
        "wall_s": time.perf_counter() - t_start,
        "values": {lab: {k: v.tolist() for k, v in d.items()} for lab, d in values.items()},
        "assumptions": [*NOTES, *sc.notes(spec.mode, thrusters=spec.judge_thrusters)],
    }
    if spec.judge_thrusters:
        result["assumptions"].append(
            "gradients and the random search on the ideal-force plant; the held-out rows "
            "'(thrusters)' fly the same tunings with the thrusters (the pulse train is "
            "piecewise constant in the parameters: no gradient through it)"
        )
    if out is not None:
        tuner.heldout_keys = k_ho  # the figures fly a held-out run with its own key
        _write(out, spec, tuner, result, history, rows, values)
        result["out"] = str(out)
    return result


def _history_row(method, step, evaluations, loss, best, aux, gnorm, wall) -> dict:
    Ls, E, T, M, m = aux
    return {
        "method": method,
        "step": step,
        "evaluations": evaluations,
        "loss": loss,
        "best_loss": float(best),
        "effort_term": float(jnp.mean(E)),
        "time_term_s": float(jnp.mean(T)),
        "margin_term": float(jnp.mean(M)),
        "docked_fraction": float(jnp.mean(m.docked)),
        "grad_norm": gnorm,
        "wall_s": wall,
    }


class _NoBar:
    def update(self, n):
        pass

    def set_postfix(self, **kw):
        pass

    def close(self):
        pass


def _bar(total, desc, progress):
    if not progress:
        return _NoBar()
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="step", leave=False)


def _write(out: Path, spec: TuneSpec, tuner: Tuner, result, history, rows, values) -> None:
    import pandas as pd

    from rvdjax import provenance  # provenance hook: code, machine and definition
    from rvdjax.tune.files import write_params

    result["provenance"] = provenance.stamp(
        None,
        provenance.describe(
            spec=spec.to_dict(), scenario=provenance.scenario_values(tuner.scenario)
        ),
    )
    pd.DataFrame(history).to_parquet(out / "history.parquet", index=False)
    pd.DataFrame(rows).to_parquet(out / "heldout.parquet", index=False)
    prov = result["provenance"]
    write_params(out / "tuned_params.json", tuner, values["tuned"], "gradient", spec, prov)
    if "random_search" in values:
        write_params(
            out / "random_params.json", tuner, values["random_search"], "random", spec, prov
        )
    (out / "spec.json").write_text(json.dumps(spec.to_dict(), indent=2, default=list))
    (out / "summary.json").write_text(json.dumps(result, indent=2))
    try:  # the tables and files are written: a failed figure must not lose them
        from rvdjax.tune.figures import tuning_figures

        tuning_figures(out, tuner, values, history, rows)
    except Exception as err:  # noqa: BLE001
        import warnings

        warnings.warn(f"tuning figures not written: {err!r}", stacklevel=2)
