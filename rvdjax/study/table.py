"""A study's tidy table on disk: one Parquet part file per flush, one row per run.

``DIR/config.json`` holds the exact :class:`~rvdjax.study.spec.StudySpec`; ``DIR/runs/`` holds
``part-P<process>-<sequence>.parquet`` files. A part is written to a temporary name and then
renamed (atomic on POSIX), so a reader never sees a half-written part and a study killed at any
moment keeps every part it finished; ``--resume`` reads the run indices already on disk and
flies only the others. pandas reads the whole table with ``pandas.read_parquet(DIR / "runs")``
(or :func:`read_table`, which also sorts by run).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

__all__ = [
    "PartWriter",
    "read_table",
    "table_columns",
    "done_runs",
    "write_config",
    "read_config",
]

RUNS_DIR = "runs"
CONFIG = "config.json"


def _atomic_write_bytes(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def write_config(out: Path, config: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    _atomic_write_bytes(out / CONFIG, json.dumps(config, indent=2, sort_keys=True).encode())


def read_config(out: Path) -> dict | None:
    p = Path(out) / CONFIG
    if not p.exists():
        return None
    return json.loads(p.read_text())


def _parts(out: Path) -> list[Path]:
    d = Path(out) / RUNS_DIR
    if not d.exists():
        return []
    return sorted(p for p in d.glob("part-*.parquet"))


def done_runs(out: Path) -> np.ndarray:
    """Run indices already written (sorted). A run written twice (never, by construction:
    parts are atomic and a resume flies only runs not on disk) raises."""
    idx = [pq.read_table(p, columns=["run"]).column("run").to_numpy() for p in _parts(out)]
    runs = np.sort(np.concatenate(idx)) if idx else np.zeros(0, np.int64)
    twice = runs[1:][runs[1:] == runs[:-1]]
    if len(twice):
        raise ValueError(f"{out}: run {int(twice[0])} is written twice ({len(twice)} duplicates)")
    return runs


def table_columns(out: Path) -> list[str]:
    """The table's column names (none before the first part is written)."""
    parts = _parts(out)
    return pq.read_schema(parts[0]).names if parts else []


def read_table(out: Path, columns=None, runs=None):
    """The study's table as a pandas DataFrame sorted by run index: every column, or
    ``columns`` (with "run"); every run, or those in ``runs``."""
    import pandas as pd

    parts = _parts(out)
    if not parts:
        raise ValueError(f"no results in {out} (no {RUNS_DIR}/part-*.parquet)")
    if columns is not None:
        columns = list(dict.fromkeys(["run", *columns]))
    filters = None if runs is None else [("run", "in", [int(r) for r in runs])]
    frames = [pq.read_table(p, columns=columns, filters=filters).to_pandas() for p in parts]
    df = pd.concat(frames, ignore_index=True)
    return df.sort_values("run", kind="stable").reset_index(drop=True)


class PartWriter:
    """Buffers columnar batches of rows (``pyarrow.Table`` s) and writes a part file when
    ``flush_rows`` rows or ``flush_s`` seconds have accumulated (and on :meth:`close`); a batch
    is written whole (a part may hold more than ``flush_rows`` rows)."""

    def __init__(self, out: Path, process: int = 0, flush_rows: int = 256, flush_s: float = 20):
        self.dir = Path(out) / RUNS_DIR
        self.dir.mkdir(parents=True, exist_ok=True)
        self.process = process
        self.flush_rows = flush_rows
        self.flush_s = flush_s
        self.batches: list[pa.Table] = []
        self.pending = 0
        self.last = time.monotonic()
        existing = [p.stem.split("-")[-1] for p in self.dir.glob(f"part-P{process:03d}-*.parquet")]
        self.seq = 1 + max((int(s) for s in existing), default=-1)
        self.written = 0

    def add(self, batch: pa.Table) -> None:
        """Add a batch of rows (list of dicts are accepted too)."""
        if not isinstance(batch, pa.Table):
            batch = pa.Table.from_pylist(batch)
        if batch.num_rows:
            self.batches.append(batch)
            self.pending += batch.num_rows
        if self.pending >= self.flush_rows or time.monotonic() - self.last >= self.flush_s:
            self.flush()

    def flush(self) -> None:
        self.last = time.monotonic()
        if not self.batches:
            return
        table = pa.concat_tables(self.batches)
        sink = pa.BufferOutputStream()
        pq.write_table(table, sink)
        path = self.dir / f"part-P{self.process:03d}-{self.seq:06d}.parquet"
        _atomic_write_bytes(path, sink.getvalue().to_pybytes())
        self.seq += 1
        self.written += table.num_rows
        self.batches, self.pending = [], 0

    def close(self) -> None:
        self.flush()
