"""The GPU benchmarks' own logic, checked without a GPU: the engine-settings variants of
sweeps/gpu_study_benchmark.py and the comparison table of sweeps/gpu_xla_flags.py."""

import importlib
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "sweeps"))


def _import(name):
    """Import a sweep script without keeping the XLA_FLAGS it sets for its own process (one
    host device per core), which this process's children would inherit."""
    saved = os.environ.get("XLA_FLAGS")
    try:
        return importlib.import_module(name)
    finally:
        if saved is None:
            os.environ.pop("XLA_FLAGS", None)
        else:
            os.environ["XLA_FLAGS"] = saved


def test_settings_variants_parse_into_engine_fields():
    gsb = _import("gpu_study_benchmark")
    got = gsb.parse_settings("slots=4096/slots=16384,iterations=8,refresh=masked")
    assert got == [
        ({"slots": 4096}, 1.0),
        ({"slots": 16384, "iterations": 8, "refresh": "masked"}, 1.0),
    ]
    assert gsb.parse_settings(None) == list(gsb.SETTINGS)
    assert "settings" not in gsb.DEFAULT_PARTS  # only when asked for
    from rvdjax.loop.engine import EngineConfig

    fields = set(EngineConfig.__dataclass_fields__)
    assert all(set(values) <= fields for values, _ in gsb.SETTINGS)


def test_xla_flags_table_compares_variants_and_their_answers(tmp_path):
    gxf = _import("gpu_xla_flags")
    n = gxf.QP_BATCH
    rows = []
    for v, us, rate in (("default", 3.31, 893.0), ("while", 3.30, 876.0)):
        rows += [
            dict(variant=v, part="throughput", maneuvers_per_s=rate, compile_s=29.0),
            dict(variant=v, part="qp", mode="accurate", batch=n, us_per_qp=us, compile_s=15.0),
            dict(variant=v, part="qp", mode="accurate", batch=1, us_per_qp=13700.0),
        ]
    rows.append(dict(variant="while", part="error", what="maneuver", error="boom"))
    J = np.linspace(1.0, 2.0, 8)
    its = np.arange(8)
    np.savez(tmp_path / "answers_default.npz", accurate_8_objective=J, accurate_8_iterations=its)
    np.savez(tmp_path / "answers_while.npz", accurate_8_objective=J, accurate_8_iterations=its)
    np.savez(
        tmp_path / "answers_other.npz",
        accurate_8_objective=J * (1 + 1e-9),
        accurate_8_iterations=its + (its == 3),
    )
    table = gxf.format_table(rows, ["default", "while"], str(tmp_path))
    lines = table.splitlines()
    assert lines[0] == "| measure | default | while |"
    assert "| thesis-vbar maneuvers/s, engine | 893 | 876 |" in lines
    assert "| µs per QP, 65 536, accurate | 3.31 | 3.3 |" in lines
    assert "| ms for one QP alone, accurate | 13.7 | 13.7 |" in lines
    assert "| QP answers against the first variant's | bits | bits |" in lines
    assert "while: error maneuver: boom" in lines
    diff = gxf._same_answers(str(tmp_path), "default", "other")
    assert diff.startswith("objective 1.0e-09") and "1 iteration counts differ" in diff
    assert gxf._same_answers(str(tmp_path), "default", "missing") == "n/a"


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--variants", "default,bogus"], "--variants: unknown 'bogus'"),
        (["--budget-s", "10"], "--budget-s: must be over 30 s"),
    ],
)
def test_xla_flags_bad_input_is_one_line_and_status_2(argv, message, capsys, tmp_path):
    gxf = _import("gpu_xla_flags")
    assert gxf.main(argv + ["--out", str(tmp_path / "out")]) == 2
    out = capsys.readouterr().out
    assert out.startswith(message) and out.count("\n") == 1
    assert not (tmp_path / "out").exists()  # nothing written, no variant started
