"""The command line (``rvdjax run``, ``list``, ``demo``, ``bench``) on tiny runs.

Most of the time here is XLA compilation, so the demo runs once with both ``--json`` and
``--plot``, and the closed-loop commands use the POSEIDYN scenario (the cheapest to compile).
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
    json.loads(out)  # with --json, stdout holds the JSON document only


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
        main(["bench", "--batch", bad])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--batch" in err and len(err.splitlines()) == 1


def test_bench_rejects_an_unknown_peer(capsys):
    """A peer's name is checked before any QP is built: one line naming --peers and the
    choices, status 2."""
    assert main(["bench", "--peers", "clarabel,hpipmm"]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1, err
    assert "--peers: 'hpipmm' is not a peer" in err and "hpipm" in err.split("choose from")[1]


@pytest.mark.parametrize(
    "argv, needles",
    [
        (["run", "--mode", "fast"], ["rvdjax run: error:", "--mode", "'accurate', 'paper'"]),
        (["run", "--device", "tpu"], ["--device", "'cpu', 'gpu'"]),
        (["run", "--n-steps", "abc"], ["--n-steps", "expected an integer, got 'abc'"]),
        (["tune", "fastmpc-3d", "--lr", "x"], ["--lr", "expected a number, got 'x'"]),
        (["study", "montecarlo", "thesis-vbar"], ["rvdjax study montecarlo: error:", "--out"]),
        (["verify"], ["rvdjax verify: error:", "required: command {worst,probability}"]),
        (["fly"], ["rvdjax: error: command: invalid choice: 'fly'", "'run'"]),
        (["verify", "worstt"], ["command: invalid choice: 'worstt'", "'probability'"]),
    ],
)
def test_argument_errors_are_one_line(argv, needles, capsys):
    """argparse's own refusals (a choice, a number, a missing argument) are one line naming
    the parameter and what it allows, status 2, as the commands' later checks are."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1, err
    for needle in needles:
        assert needle in err, (needle, err)


def test_closed_loop_bench_json(tmp_path, capsys):
    """``rvdjax bench --closed-loop --json`` on a tiny run: the rows the issue asks for."""
    out = tmp_path / "bench.json"
    args = [
        "bench",
        "--closed-loop",
        "--scenarios",
        "poseidyn-lqmpc",
        "--batch",
        "2",
        "--runs",
        "2",
        "--single-runs",
        "1",
        "--json",
        "--out",
        str(out),
    ]
    assert main(args) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["batch"] for r in rows] == [1, 2]
    for r in rows:
        for key in (
            "scenario",
            "family",
            "batch",
            "runs",
            "maneuvers_per_s",
            "peak_memory_mb",
            "docked_fraction",
            "mean_iterations",
        ):
            assert key in r, key
        assert r["scenario"] == "poseidyn-lqmpc" and r["family"] == "poseidyn"
        assert r["docked_fraction"] == 1.0 and r["maneuvers_per_s"] > 0
    assert rows[1]["peak_memory_mb"] > 0
    doc = json.loads(out.read_text())
    assert doc["rows"][0]["scenario"] == "poseidyn-lqmpc"
    # the file says which code, machine and options measured it
    from rvdjax import provenance

    prov = doc["provenance"]
    env = prov["environments"][prov["first"]]
    assert env["source_sha256"] == provenance.source_sha256() and env["device"] == "cpu"
    options = prov["definition"]["options"]
    assert prov["definition"]["benchmark"] == "rvdjax bench" and options["closed_loop"] is True
    assert prov["definition_sha256"] == provenance.digest(prov["definition"])


@pytest.mark.parametrize(
    "args, word",
    [
        (["run", "--plot", "/no/such/dir/p.png"], "does not exist"),
        (["run", "--plot", "plot.txt"], "must end in"),
        (["demo", "--plot", "/no/such/dir/p.png"], "does not exist"),
        (["bench", "--closed-loop", "--out", "/no/such/dir/b.json"], "does not exist"),
        (["run", "no-such-scenario"], "unknown scenario"),
        # /proc takes no new file, whoever asks (os.access says yes to root)
        (["run", "spot-2d-a", "--plot", "/proc/x.png"], "cannot write in"),
        (["study", "montecarlo", "spot-2d-a", "--runs", "10", "--out", "/proc/x"], "cannot write"),
        (["study", "montecarlo", "spot-2d-a", "--out", "o", "--plots", "/proc/p"], "cannot write"),
        (["tune", "poseidyn-lqmpc", "--out", "/proc/y"], "cannot write in"),
        (["bench", "--closed-loop", "--scenarios", "nope"], "unknown scenario"),
    ],
)
def test_bad_output_paths_fail_before_any_work(args, word, capsys):
    """Output paths and names are checked before anything is flown or compiled."""
    import time

    t0 = time.perf_counter()
    assert main(args) == 2
    assert word in capsys.readouterr().err
    assert time.perf_counter() - t0 < 5.0


def test_output_path_that_is_a_directory(tmp_path, capsys):
    d = tmp_path / "plot.png"
    d.mkdir()
    assert main(["run", "--plot", str(d)]) == 2
    assert "is a directory" in capsys.readouterr().err


def test_list_names_every_scenario(capsys):
    from rvdjax.scenarios import SCENARIOS

    assert main(["list"]) == 0
    out = capsys.readouterr().out
    # one line per scenario, its name as the first word (long names stay separate)
    assert [line.split()[0] for line in out.splitlines()] == list(SCENARIOS)


def test_run_command_json_and_plot(capsys, tmp_path):
    plot = tmp_path / "run.png"
    assert main(["run", "poseidyn-lqmpc", "--json", "--plot", str(plot)]) == 0
    out = json.loads(capsys.readouterr().out)
    for key in (
        "scenario",
        "family",
        "status",
        "docked",
        "delta_v_m_s",
        "total_impulse_N_s",
        "effort_l1_N_s",
        "time_to_dock_s",
        "max_violation_m",
        "margins_m",
        "solver_status_counts",
        "mean_solve_ms",
        "published",
        "assumptions",
        "comparison",
    ):
        assert key in out, key
    assert out["scenario"] == "poseidyn-lqmpc" and out["docked"] is True
    assert out["status"] == "docked" and out["family"] == "poseidyn"
    assert {c["figure"] for c in out["comparison"]} >= {"effort_l1_N_s vs LQ-MPC (sim)"}
    assert plot.stat().st_size > 10_000 and plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_run_disturbed_json(capsys):
    """`rvdjax run NAME --disturbed --seed S`: noise and thrust error from PRNG key S; the
    JSON says so and lists the disturbance assumptions."""
    assert main(["run", "poseidyn-lqmpc", "--disturbed", "--seed", "4", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["disturbed"] is True and out["seed"] == 4
    assert out["docked"] is True and np.isfinite(out["effort_l1_N_s"])
    assert any("Gauss-Markov" in a for a in out["assumptions"])


def test_a_reader_that_stops_early_gets_no_traceback():
    """`rvdjax ... | head`: the pipe closes while the command still prints; the command ends
    with status 141 (a closed pipe), no traceback on stderr."""
    import subprocess
    import sys

    child = (
        "import sys\n"
        "import rvdjax.cli.scenarios as m\n"
        "def flood(args):\n"
        "    for _ in range(20000):\n"
        "        print('x' * 100)\n"
        "    return 0\n"
        "m.cmd_list = flood\n"
        "from rvdjax.cli import main\n"
        "sys.exit(main(['list']))\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", child], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    proc.stdout.read(200)  # read a little, then stop reading: the pipe fills and closes
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141
    assert "Traceback" not in err and "BrokenPipeError" not in err
