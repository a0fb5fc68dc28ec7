"""A verification's evaluations on disk, written as they are made and read back on resume.

``DIR/config.json`` holds the verification's specification; ``DIR/evals/part-*.parquet``
hold one row per closed-loop evaluation: its run number (``run``, the argument of
``rvdjax run SCENARIO --study DIR --run R``), the method and batch it belongs to, the
dispersion vector xi, the exact margin, the smooth margin and its gradient (gradient
evaluations), and the run's main figures.

Every method is deterministic given its seed, so a resumed method asks for the same batches
in the same order: :meth:`EvalStore.evaluate` returns a batch found on disk (after checking
that its xi are the ones asked for) instead of flying it again.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from rvdjax.study.table import _atomic_write_bytes

__all__ = ["EvalStore", "read_evals", "CONFIG", "EVALS"]

CONFIG = "config.json"
EVALS = "evals"


def _rows(key: str, method: str, first_run: int, xis, res: dict, effort_key: str) -> list[dict]:
    m = res.get("metrics")
    rows = []
    for i in range(len(xis)):
        row = {
            "run": first_run + i,
            "batch": key,
            "row": i,
            "method": method,
            "xi": [float(v) for v in xis[i]],
            "margin": float(res["margin"][i]),
            "smooth": float(res["smooth"][i]) if "smooth" in res else None,
            "grad": [float(v) for v in res["grad"][i]] if "grad" in res else None,
        }
        if m is not None:
            row.update(
                docked=bool(m.docked[i]),
                status=int(m.status[i]),
                steps=int(m.steps[i]),
                time_to_dock_s=float(m.time_to_dock_s[i]),
                effort=float(np.asarray(getattr(m, effort_key))[i]),
                max_violation_m=float(m.max_violation_m[i]),
            )
        rows.append(row)
    return rows


class EvalStore:
    """Evaluations of one verification directory (or in memory when ``out`` is None)."""

    def __init__(self, out=None, effort_key: str = "delta_v_m_s"):
        self.out = None if out is None else Path(out)
        self.effort_key = effort_key
        self.batches: dict[str, dict] = {}
        self.next_run = 0
        self.seq = 0
        if self.out is not None:
            (self.out / EVALS).mkdir(parents=True, exist_ok=True)
            parts = sorted((self.out / EVALS).glob("part-*.parquet"))
            self.seq = len(parts)
            for p in parts:
                df = pq.read_table(p).to_pandas()
                for key, g in df.groupby("batch", sort=False):
                    g = g.sort_values("row")
                    self.batches[key] = {
                        "run": g["run"].to_numpy(),
                        "xi": np.stack(g["xi"].to_numpy()),
                        "margin": g["margin"].to_numpy(float),
                        "smooth": g["smooth"].to_numpy(float),
                        "grad": (
                            np.stack(g["grad"].to_numpy()) if g["grad"].notna().all() else None
                        ),
                    }
                    self.next_run = max(self.next_run, int(g["run"].max()) + 1)

    def __contains__(self, key: str) -> bool:
        return key in self.batches

    def evaluate(self, key: str, method: str, xis, fn) -> dict:
        """``fn(xis)`` (a :class:`~rvdjax.verify.evaluate.Problem` evaluator's result), or the
        batch ``key`` read back from disk. Adds "run" (the rows' run numbers)."""
        xis = np.asarray(xis, float)
        if key in self.batches:
            b = self.batches[key]
            if b["xi"].shape != xis.shape or not np.allclose(b["xi"], xis, rtol=0, atol=1e-12):
                raise ValueError(
                    f"{self.out}: batch {key} on disk was flown at other points; this directory "
                    "holds a different verification (choose another --out)"
                )
            out = {"margin": b["margin"], "run": b["run"], "xi": xis}
            if not np.all(np.isnan(b["smooth"])):
                out["smooth"] = b["smooth"]
            if b["grad"] is not None:
                out["grad"] = b["grad"]
            return out
        res = fn(xis)
        first = self.next_run
        self.next_run += len(xis)
        rows = _rows(key, method, first, xis, res, self.effort_key)
        if self.out is not None:
            table = pa.Table.from_pylist(rows)
            sink = pa.BufferOutputStream()
            pq.write_table(table, sink)
            path = self.out / EVALS / f"part-{self.seq:06d}.parquet"
            _atomic_write_bytes(path, sink.getvalue().to_pybytes())
            self.seq += 1
        out = {k: v for k, v in res.items() if k != "metrics"}
        out["run"] = np.arange(first, first + len(xis))
        out["xi"] = xis
        self.batches[key] = {
            "run": out["run"],
            "xi": xis,
            "margin": np.asarray(res["margin"], float),
            "smooth": np.asarray(res.get("smooth", np.full(len(xis), np.nan)), float),
            "grad": res.get("grad"),
        }
        return out


def read_evals(out):
    """Every evaluation of a verification directory as a pandas DataFrame sorted by run."""
    import pandas as pd

    parts = sorted((Path(out) / EVALS).glob("part-*.parquet"))
    if not parts:
        raise ValueError(f"no evaluations in {out} (no {EVALS}/part-*.parquet)")
    df = pd.concat([pq.read_table(p).to_pandas() for p in parts], ignore_index=True)
    return df.sort_values("run", kind="stable").reset_index(drop=True)


def write_json(path: Path, obj) -> None:
    _atomic_write_bytes(Path(path), json.dumps(obj, indent=2, sort_keys=True).encode())
