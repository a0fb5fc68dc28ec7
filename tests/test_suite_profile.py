"""sweeps/suite_profile.py's tables, from events and a JUnit file written here."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "sweeps"))
import suite_profile as sp  # noqa: E402

A = "tests/test_a.py::test_one"
B = "tests/test_b.py::test_two[x]"


def _write(tmp_path: Path):
    events = tmp_path / "events"
    events.mkdir()
    (events / "11.tsv").write_text(
        f"{A}\tbackend_compile_duration\tjit(big)\t2.0\n"
        f"{A}\tjaxpr_trace_duration\tbig\t0.5\n"
        f"{A}\tjaxpr_to_mlir_module_duration\tjit(big)\t0.25\n"
        f"{A}\tbackend_compile_duration\tjit(add)\t0.07\n"
        f"{A}\tcache_retrieval_time_sec\t\t9.0\n"  # not a compile-pipeline event
        "torn line without tabs\n"
    )
    (events / "12.tsv").write_text(
        f"{B}\tbackend_compile_duration\tjit(add)\t0.03\n"
        f"{B}\tjaxpr_to_mlir_module_duration\tjit(add)\t0.01\n"
        f"{B}\tbackend_compile_duration\tjit(big)\t4.0\n"
    )
    (tmp_path / "junit.xml").write_text(
        '<testsuites><testsuite><testcase classname="tests.test_a" name="test_one" time="5.0"/>'
        '<testcase classname="tests.test_b" name="test_two[x]" time="3.5"/>'
        '<testcase classname="tests.test_b" name="test_three" time="1.5"/></testsuite>'
        "</testsuites>"
    )
    return sp.read_events(events), sp.read_junit(tmp_path / "junit.xml")


def test_events_are_summed_per_file_and_per_program(tmp_path):
    events, times = _write(tmp_path)
    assert len(events) == 7  # the retrieval event and the torn line left out
    assert times == {"test_a.py": 5.0, "test_b.py": 5.0}
    programs = sp.program_stats(events)
    # tracing names the function, compiling its jit: one program
    assert programs["big"]["compiles"] == 2 and programs["big"]["trace"] == 0.5
    assert programs["big"]["compile"] == pytest.approx(6.0)
    files = sp.file_stats(events)
    a, b = files["test_a.py"], files["test_b.py"]
    assert (a["compiles"], b["compiles"]) == (2, 2)
    assert a["compile"] == pytest.approx(2.07) and a["lower"] == pytest.approx(0.25)
    # "add": 2 compiles, (0.07 + 0.03 + 0.01) / 2 s each with its lowering: one operation;
    # "big" (3 s a compile) is not
    assert a["small"] == pytest.approx(0.07) and b["small"] == pytest.approx(0.04)
    table = sp.report(events, times, top=5)
    total = next(line for line in table.splitlines() if line.startswith("all files"))
    # test time 10, 4 compiles, 6.1 s compiling, 0.5 tracing, 0.26 lowering, 0.11 of it one
    # operation, the rest 3.14
    assert total.split()[2:] == ["10.0", "4", "6.1", "0.5", "0.3", "0.1", "3.1"]


def test_a_bad_top_or_an_unwritable_out_exits_2(tmp_path, capsys):
    assert sp.main(["--top", "0"]) == 2
    assert "--top must be >= 1" in capsys.readouterr().err
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert sp.main(["--out", str(blocker / "sub")]) == 2
    assert capsys.readouterr().err.startswith("--out: cannot write to")
