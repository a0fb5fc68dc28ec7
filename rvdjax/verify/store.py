"""A verification's evaluations on disk, written as they are made and read back on resume.

``DIR/config.json`` holds the verification's specification; ``DIR/evals/part-*.parquet``
hold one row per closed-loop evaluation: its run number (``run``, the argument of
``rvdjax run SCENARIO --study DIR --run R``), the method and batch it belongs to, the
dispersion vector xi, the exact margin, the smooth margin and its gradient (gradient
evaluations), and the run's main figures.

Every method is deterministic given its seed, so a resumed method asks for the same batches
in the same order: :meth:`EvalStore.evaluate` returns a batch found on disk (after checking
that its xi are the ones asked for) instead of flying it again.

``DIR/provenance.json`` (:mod:`rvdjax.provenance`) holds the definition of the runs (the
problem's scenario values, parameters, loop, solver, requirement and dispersion) and the code
and machine that flew them. A store opened with another definition stops with one line naming
what differs, and one opened by another code version stops unless ``allow_code_change``; every
row carries ``provenance`` (the environment that flew it) and ``code_changed``.
"""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from rvdjax import provenance
from rvdjax.study.table import _atomic_write_bytes

__all__ = ["EvalStore", "read_evals", "CONFIG", "EVALS", "PROVENANCE"]

CONFIG = "config.json"
EVALS = "evals"
PROVENANCE = "provenance.json"


def _rows(
    key: str, method: str, first_run: int, xis, res: dict, effort_key: str, marks: dict
) -> list[dict]:
    m = res.get("metrics")
    rows = []
    for i in range(len(xis)):
        row = {
            **marks,
            "run": first_run + i,
            "batch": key,
            "row": i,
            "method": method,
            "xi": [float(v) for v in xis[i]],
            "margin": float(res["margin"][i]),
            "smooth": float(res["smooth"][i]) if "smooth" in res else None,
            "grad": [float(v) for v in res["grad"][i]] if "grad" in res else None,
        }
        if "zeroed" in res:  # gradient evaluations: what was zeroed, counted
            row["zeroed_backsolves"] = int(res["zeroed"][i])
            row["nonfinite_gradient"] = bool(res["nonfinite"][i])
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
    """Evaluations of one verification directory (or in memory when ``out`` is None).

    ``definition``: what defines the runs (:meth:`~rvdjax.verify.evaluate.Problem.definition`,
    plus whatever else the caller's batches depend on); required for a directory. A directory
    holding another definition, or flown by another code version without
    ``allow_code_change``, raises :class:`~rvdjax.provenance.ProvenanceError` (one line)."""

    def __init__(
        self,
        out=None,
        effort_key: str = "delta_v_m_s",
        definition: dict | None = None,
        allow_code_change: bool = False,
    ):
        self.out = None if out is None else Path(out)
        self.effort_key = effort_key
        self.batches: dict[str, dict] = {}
        self.next_run = 0
        self.seq = 0
        self.block: dict | None = None
        self.marks: dict = {}
        self.used: Counter = Counter()  # rows handed out, by the environment that flew them
        if self.out is not None:
            if definition is None:
                raise ValueError(f"{self.out}: a store on disk needs its runs' definition")
            (self.out / EVALS).mkdir(parents=True, exist_ok=True)
            parts = sorted((self.out / EVALS).glob("part-*.parquet"))
            path = self.out / PROVENANCE
            stored = json.loads(path.read_text()) if path.exists() else ({} if parts else None)
            self.block = provenance.stamp(
                stored, definition, allow_code_change=allow_code_change, where=str(self.out)
            )
            write_json(path, self.block)
            self.marks = provenance.row_marks(self.block)
            self.seq = len(parts)
            for p in parts:
                df = pq.read_table(p).to_pandas()
                if "provenance" not in df:
                    df["provenance"] = "unrecorded"
                for key, g in df.groupby("batch", sort=False):
                    g = g.sort_values("row")
                    self.batches[key] = {
                        "env": g["provenance"].to_numpy(str),
                        "run": g["run"].to_numpy(),
                        "xi": np.stack(g["xi"].to_numpy()),
                        "margin": g["margin"].to_numpy(float),
                        "smooth": g["smooth"].to_numpy(float),
                        "grad": (
                            np.stack(g["grad"].to_numpy()) if g["grad"].notna().all() else None
                        ),
                        **(
                            {
                                "zeroed": g["zeroed_backsolves"].to_numpy(int),
                                "nonfinite": g["nonfinite_gradient"].to_numpy(bool),
                            }
                            if "zeroed_backsolves" in g and g["zeroed_backsolves"].notna().all()
                            else {}
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
            self.used.update(b["env"].tolist())
            out = {"margin": b["margin"], "run": b["run"], "xi": xis}
            if not np.all(np.isnan(b["smooth"])):
                out["smooth"] = b["smooth"]
            if b["grad"] is not None:
                out["grad"] = b["grad"]
            for k in ("zeroed", "nonfinite"):
                if k in b:
                    out[k] = b[k]
            return out
        res = fn(xis)
        first = self.next_run
        self.next_run += len(xis)
        rows = _rows(key, method, first, xis, res, self.effort_key, self.marks)
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
        env = self.marks.get("provenance", "memory")
        self.used[env] += len(xis)
        self.batches[key] = {
            "env": np.full(len(xis), env),
            "run": out["run"],
            "xi": xis,
            "margin": np.asarray(res["margin"], float),
            "smooth": np.asarray(res.get("smooth", np.full(len(xis), np.nan)), float),
            "grad": res.get("grad"),
            **{k: np.asarray(res[k]) for k in ("zeroed", "nonfinite") if k in res},
        }
        return out

    def provenance_summary(self) -> dict | None:
        """The directory's provenance with the rows this store handed out, by environment
        (None in memory)."""
        if self.block is None:
            return None
        envs = self.block["environments"]
        first = provenance.code_identity(envs[self.block["first"]])
        changed = sum(
            n
            for e, n in self.used.items()
            if e not in envs or provenance.code_identity(envs[e]) != first
        )
        return {**self.block, "rows_used": dict(self.used), "rows_code_changed": changed}


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
