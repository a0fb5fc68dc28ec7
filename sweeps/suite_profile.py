"""Where the test suite's time goes: XLA's compiles, tracing and lowering per test file and per
program, beside each file's test time (docs/history.md, "Where the suite's time goes on a
slower VM").

    python sweeps/suite_profile.py [--out DIR] [--top 20] [-- PYTEST ARGS...]

Runs ``pytest`` (the README's command with the project's addopts, plus any arguments after
``--``) with a listener on ``jax.monitoring``'s duration events in every process it starts:
the xdist workers and their child interpreters (notebooks, studies, the command line), through
a ``sitecustomize`` module put first on ``PYTHONPATH``. Each event is filed under the test that
was running (``PYTEST_CURRENT_TEST``, which a child process inherits with its environment; a
child started from a fixture's environment files its events under the test that built it).
Writes DIR/events/PID.tsv (test, event, program, seconds) and DIR/junit.xml, and prints two
tables: per test file, its test time and the compiler's share of it (backend compile, tracing,
lowering to StableHLO, and the one-operation programs among them); per program name, its
compiles and their seconds. The VM's speed moves between runs: compare compile counts and
the compiler's seconds back to back, not one run's wall time against another's.
"""

from __future__ import annotations

import argparse
import collections
import os
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
EVENTS_ENV = "RVDJAX_SUITE_EVENTS"
PHASES = {
    "backend_compile_duration": "compile",
    "jaxpr_trace_duration": "trace",
    "jaxpr_to_mlir_module_duration": "lower",
}
# a program whose compile and lowering take less than this (s) is counted as one operation
SMALL_S = 0.06

SITECUSTOMIZE = f'''
import os

_out = os.environ.get("{EVENTS_ENV}")
if _out:
    _file = []

    def _listener(event, duration, **kw):
        if not _file:
            _file.append(open(os.path.join(_out, f"{{os.getpid()}}.tsv"), "a", buffering=1))
        test = os.environ.get("PYTEST_CURRENT_TEST", "-").split(" (")[0]
        _file[0].write(f"{{test}}\\t{{event.rsplit('/', 1)[-1]}}\\t{{kw.get('fun_name', '')}}\\t"
                       f"{{duration}}\\n")

    try:
        import jax.monitoring

        jax.monitoring.register_event_duration_secs_listener(_listener)
    except Exception:  # a Python without jax (a tool pytest starts): nothing to record
        pass
'''


def read_events(directory: Path) -> list[tuple[str, str, str, float]]:
    """(test node id, phase, program name, seconds) of every compile-pipeline event."""
    rows = []
    for path in sorted(directory.glob("*.tsv")):
        for line in path.read_text().splitlines():
            parts = line.split("\t")
            if len(parts) == 4 and parts[1] in PHASES:
                test, event, name, secs = parts
                # tracing names the function, compiling and lowering its jit: one key for both
                name = name[4:-1] if name.startswith("jit(") and name.endswith(")") else name
                rows.append((test, PHASES[event], name, float(secs)))
    return rows


def read_junit(path: Path) -> dict[str, float]:
    """Test time (s) per test file, from pytest's JUnit XML."""
    times: dict[str, float] = collections.Counter()
    for case in ET.parse(path).iter("testcase"):
        times[case.get("classname", "").split(".")[-1] + ".py"] += float(case.get("time", 0))
    return times


def program_stats(events) -> dict[str, dict[str, float]]:
    """Per program name: compiles and the seconds of each phase."""
    out: dict[str, dict[str, float]] = collections.defaultdict(collections.Counter)
    for _, phase, program, secs in events:
        out[program][phase] += secs
        out[program]["compiles"] += phase == "compile"
    return out


def file_stats(events) -> dict[str, dict[str, float]]:
    """Per test file: the seconds of each phase, compiles, and the seconds of the programs
    that compile and lower in under SMALL_S on average (one operation each)."""
    programs = program_stats(events)
    small = {
        name
        for name, s in programs.items()
        if s["compiles"] and (s["compile"] + s["lower"]) / s["compiles"] < SMALL_S
    }
    out: dict[str, dict[str, float]] = collections.defaultdict(collections.Counter)
    for test, phase, program, secs in events:
        name = test.split("::")[0].rsplit("/", 1)[-1]
        out[name][phase] += secs
        out[name]["compiles"] += phase == "compile"
        if program in small and phase in ("compile", "lower"):
            out[name]["small"] += secs
    return out


def report(events, times: dict[str, float], top: int = 20) -> str:
    files = file_stats(events)
    lines = [
        f"{'test file':<28} {'test s':>7} {'compiles':>8} {'compile':>8} {'trace':>7} "
        f"{'lower':>7} {'1-op':>6} {'rest':>7}"
    ]
    names = sorted(set(files) | set(times), key=lambda n: -times.get(n, 0.0))
    total = collections.Counter()
    for name in names:
        s, t = files.get(name, collections.Counter()), times.get(name, 0.0)
        pipeline = s["compile"] + s["trace"] + s["lower"]
        row = (t, s["compiles"], s["compile"], s["trace"], s["lower"], s["small"], t - pipeline)
        total.update(dict(zip(("t", "n", "c", "tr", "lo", "sm", "r"), row, strict=True)))
        if len(lines) <= top:
            lines.append(
                f"{name:<28} {row[0]:7.1f} {row[1]:8.0f} {row[2]:8.1f} {row[3]:7.1f} "
                f"{row[4]:7.1f} {row[5]:6.1f} {row[6]:7.1f}"
            )
    lines.append(
        f"{'all files':<28} {total['t']:7.1f} {total['n']:8.0f} {total['c']:8.1f} "
        f"{total['tr']:7.1f} {total['lo']:7.1f} {total['sm']:6.1f} {total['r']:7.1f}"
    )
    lines += ["", f"{'program':<36} {'compiles':>8} {'compile':>8} {'trace':>7} {'lower':>7}"]
    programs = program_stats(events)
    by_cost = sorted(programs.items(), key=lambda kv: -sum(kv[1][p] for p in PHASES.values()))
    for name, s in by_cost[:top]:
        lines.append(
            f"{name[:36]:<36} {s['compiles']:8.0f} {s['compile']:8.1f} {s['trace']:7.1f} "
            f"{s['lower']:7.1f}"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=None, help="directory for the events and junit.xml")
    ap.add_argument("--top", type=int, default=20, help="rows of each table (>= 1)")
    args = ap.parse_args(argv[: argv.index("--")] if "--" in argv else argv)
    if args.top < 1:
        print(f"--top must be >= 1, got {args.top}", file=sys.stderr)
        return 2
    out = args.out or Path(tempfile.mkdtemp(prefix="rvdjax-suite-"))
    try:
        (out / "events").mkdir(parents=True, exist_ok=True)
        (out / "site").mkdir(exist_ok=True)
        (out / "site" / "sitecustomize.py").write_text(SITECUSTOMIZE)
    except OSError as err:
        print(f"--out: cannot write to {out} ({err.strerror})", file=sys.stderr)
        return 2
    for old in (out / "events").glob("*.tsv"):
        old.unlink()
    path = os.pathsep.join(p for p in (str(out / "site"), os.environ.get("PYTHONPATH")) if p)
    env = dict(os.environ, PYTHONPATH=path, **{EVENTS_ENV: str(out / "events")})
    cmd = [sys.executable, "-m", "pytest", f"--junitxml={out / 'junit.xml'}", *extra]
    t0 = time.perf_counter()
    rc = subprocess.run(cmd, cwd=ROOT, env=env).returncode
    wall = time.perf_counter() - t0
    events = read_events(out / "events")
    times = read_junit(out / "junit.xml") if (out / "junit.xml").exists() else {}
    print(f"\npytest exited {rc} after {wall:.1f} s of wall time; events and JUnit XML in {out}\n")
    print(report(events, times, args.top))
    return rc


if __name__ == "__main__":
    sys.exit(main())
