"""The command line (``rvdjax demo``, ``rvdjax bench``) and the benchmark driver, on tiny runs.

Most of the time here is XLA compilation (every ``demo`` call and every benchmark row jits a
fresh N = 30 solve, ~3-5 s each), so the demo runs once with both ``--json`` and ``--plot``
and the benchmark's memory column (a second compile per row) is stubbed out.
"""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest

from rvdjax.bench import BenchConfig, format_table, run_benchmark
from rvdjax.cli import main

BENCH_KEYS = (
    "solver",
    "mode",
    "batch",
    "N",
    "ms_per_problem",
    "solves_per_s",
    "rel_objective_gap",
    "max_violation",
    "iterations",
)


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    """(return code, stdout, plot path) of ``rvdjax demo --json --plot FILE``."""
    png = tmp_path_factory.mktemp("demo") / "p.png"
    buf = io.StringIO()  # capsys is function-scoped: capture by hand for the module fixture
    with contextlib.redirect_stdout(buf):
        rc = main(["demo", "--json", "--plot", str(png)])
    return rc, buf.getvalue(), png


def test_demo_json(demo_run):
    rc, out, _ = demo_run
    assert rc == 0
    # The JSON document comes first; the plot message follows it.
    doc, _ = json.JSONDecoder().raw_decode(out)
    rows = {r["solver"]: r for r in doc["rows"]}
    assert set(rows) == {"rvdjax-accurate", "rvdjax-paper", "clarabel"}
    acc = rows["rvdjax-accurate"]
    assert acc["status"] == "converged"
    assert abs(acc["rel_gap_to_clarabel"]) < 1e-6
    assert acc["max_violation"] <= 1e-6
    assert rows["rvdjax-paper"]["iterations"] <= 10
    for r in rows.values():
        assert r["objective"] > 0


def test_demo_plot(demo_run):
    _, out, png = demo_run
    assert png.exists() and png.stat().st_size > 1000
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert f"plot written to {png}" in out


def test_demo_rejects_unknown_flag(capsys):
    with pytest.raises(SystemExit):
        main(["demo", "--bogus"])
    assert "unrecognized arguments" in capsys.readouterr().err


def test_run_benchmark_tiny():
    messages = []
    rows = run_benchmark(
        BenchConfig(batches=(4,), horizons=(30,), n_peer=2, peers=("clarabel",), repeats=1),
        progress=messages.append,
    )
    assert messages  # progress is reported
    for r in rows:
        missing = [k for k in BENCH_KEYS if k not in r]
        assert not missing, (r["solver"], missing)
    solvers = {(r["solver"], r["mode"], r["batch"]) for r in rows}
    assert ("clarabel", "default", 1) in solvers
    for mode in ("accurate", "paper"):
        assert ("rvdjax", mode, 1) in solvers and ("rvdjax", mode, 4) in solvers
    accurate = [r for r in rows if r["solver"] == "rvdjax" and r["mode"] == "accurate"]
    for r in accurate:
        assert r["rel_objective_gap"] < 1e-6
        assert r["max_violation"] <= 1e-6
        assert r["N"] == 30 and r["ms_per_problem"] > 0 and r["solves_per_s"] > 0
        assert r["mem_MB"] > 0 or np.isnan(r["mem_MB"])  # XLA's plan; backend dependent
    table = format_table(rows)
    lines = table.splitlines()
    assert len(lines) == len(rows) + 1  # header + one line per row
    for r, line in zip(rows, lines[1:], strict=True):
        assert line.startswith(r["solver"])


@pytest.mark.parametrize("bad", ["0", "-3", "4,x", ""])
def test_bench_rejects_bad_batches(bad, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["bench", "--batches", bad])
    assert exc.value.code == 2
    assert "--batches" in capsys.readouterr().err


def test_no_command_is_an_error(capsys):
    with pytest.raises(SystemExit):
        main([])
