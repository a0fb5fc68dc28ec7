"""Provenance of stored results: canonical definitions, refusals in one line, marked rows."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rvdjax import provenance
from rvdjax.cli import main
from rvdjax.provenance import ProvenanceError


def test_canonical_definitions_hash_values_not_rounding():
    """Equal values give equal digests (floats to 12 digits, arrays by value); a change in
    one entry is named by its path."""
    a = {"Q": np.diag([1.0, 2.0, 3.0]), "big": np.arange(40.0), "ts": 0.1 + 0.2}
    b = {"Q": np.diag([1.0, 2.0, 3.0]), "big": np.arange(40.0) + 1e-15, "ts": 0.3}
    assert provenance.digest(a) == provenance.digest(b)
    c = {**b, "big": np.arange(40.0) * 2}
    assert provenance.digest(a) != provenance.digest(c)
    diff = provenance.differences(provenance.describe(**a), provenance.describe(**c))
    assert len(diff) == 1 and diff[0].startswith("big: array (40,)")
    d = provenance.describe(**{**a, "Q": np.diag([1.0, 2.0, 4.0])})
    assert provenance.differences(provenance.describe(**a), d) == ["Q[2][2]: 3.0 -> 4.0"]


@pytest.fixture
def other_code(monkeypatch):
    """The environment as another code version would record it."""

    def patch():
        env = dict(provenance._static_environment())
        env["source_sha256"] = "0" * 64
        monkeypatch.setattr(provenance, "_static_environment", lambda: env)

    return patch


def test_stamp_refuses_another_definition_or_code_in_one_line(other_code):
    block = provenance.stamp(None, {"requirement": "keep-out", "n": 3}, where="--out D")
    assert provenance.row_marks(block)["code_changed"] is False
    with pytest.raises(ProvenanceError) as e:
        provenance.stamp(block, {"requirement": "keep-out>=-10", "n": 3}, where="--out D")
    msg = str(e.value)
    assert len(msg.splitlines()) == 1 and "requirement" in msg and "keep-out>=-10" in msg
    assert provenance.stamp(block, {"requirement": "keep-out", "n": 3}) == block
    other_code()
    with pytest.raises(ProvenanceError, match="--allow-code-change") as e:
        provenance.stamp(block, {"requirement": "keep-out", "n": 3})
    assert "source_sha256" in str(e.value) and len(str(e.value).splitlines()) == 1
    again = provenance.stamp(block, {"requirement": "keep-out", "n": 3}, allow_code_change=True)
    assert again["first"] == block["first"] and again["current"] != block["first"]
    assert provenance.row_marks(again) == {"provenance": again["current"], "code_changed": True}
    lines = provenance.format_provenance(again)
    assert any("[code changed]" in line for line in lines)


def test_environment_names_code_and_machine():
    env = provenance.environment()
    for key in ("rvdjax", "source_sha256", "git_commit", "git_dirty", "jax", "jaxlib", "device"):
        assert key in env
    assert len(env["source_sha256"]) == 64 and env["device"].startswith("cpu")
    assert env["source_sha256"] == provenance.source_sha256()


def test_study_resume_refuses_other_code_and_marks_allowed_rows(tmp_path, other_code):
    from rvdjax.study import format_summary, run_study, summarize
    from rvdjax.study.spec import StudySpec
    from rvdjax.study.table import read_config, read_table

    base = dict(kind="montecarlo", scenario="fastmpc-3d-free", n_steps=25, slots=4, chunk=4)
    out = tmp_path / "s"
    run_study(StudySpec(n_initial=2, **base), out, progress=False)
    config = read_config(out)
    env = config["provenance"]["environments"][config["provenance"]["first"]]
    assert env["source_sha256"] == provenance.source_sha256()
    df = read_table(out)
    assert (df["provenance"] == config["provenance"]["first"]).all()
    assert not df["code_changed"].any()
    prov = summarize(out)["provenance"]  # the summary counts the table's own marks
    assert prov["rows_used"] == {config["provenance"]["first"]: 2}
    assert prov["rows_code_changed"] == 0
    other_code()
    spec = StudySpec(n_initial=4, **base)
    with pytest.raises(ValueError, match="different study"):  # the spec: named
        run_study(spec, out, resume=True, progress=False)
    spec = StudySpec(n_initial=2, **base)
    with pytest.raises(ProvenanceError, match="another code version"):
        run_study(spec, out, resume=True, progress=False)
    # allowed: nothing left to fly, the directory records the new code as current
    run_study(spec, out, resume=True, progress=False, allow_code_change=True)
    s = summarize(out)
    assert len(s["provenance"]["environments"]) == 2
    assert s["provenance"]["rows_code_changed"] == 0  # no row was flown by the new code
    text = format_summary(s)
    assert "provenance:" in text and "[code changed]" in text
    assert "rows were flown by another code version" not in text


def test_verification_resume_refuses_a_changed_requirement(tmp_path, capsys, other_code):
    out = tmp_path / "v"
    argv = [
        "verify", "probability", "poseidyn-lqmpc", "--dispersion", "x0:0.05,0.005",
        "--n-steps", "30", "--method", "mc", "--budget", "12", "--out", str(out), "--quiet",
    ]  # fmt: skip
    assert main([*argv, "--requirement", "keep-out"]) == 0
    printed = capsys.readouterr().out
    assert "provenance:" in printed and "definition sha256" in printed
    assert main([*argv, "--requirement", "keep-out>=-0.1", "--resume"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "threshold: 0.0 -> -0.1" in err
    other_code()
    assert main([*argv, "--requirement", "keep-out", "--resume"]) == 2
    assert "--allow-code-change" in capsys.readouterr().err
    assert main([*argv, "--requirement", "keep-out", "--resume", "--allow-code-change"]) == 0
    prov = json.loads((out / "summary.json").read_text())["provenance"]
    assert len(prov["environments"]) == 2 and prov["current"] != prov["first"]
    assert prov["rows_used"] == {prov["first"]: 12} and prov["rows_code_changed"] == 0


def test_evaluation_store_marks_rows_of_another_code(tmp_path, other_code):
    from rvdjax.verify.store import EvalStore, read_evals

    def fn(xis):
        return {"margin": xis[:, 0]}

    defn = {"problem": "x0 margin"}
    EvalStore(tmp_path, "x", defn).evaluate("a", "mc", np.ones((3, 2)), fn)
    with pytest.raises(ProvenanceError, match="defined differently"):
        EvalStore(tmp_path, "x", {"problem": "x1 margin"})
    other_code()
    with pytest.raises(ProvenanceError, match="another code version"):
        EvalStore(tmp_path, "x", defn)
    store = EvalStore(tmp_path, "x", defn, allow_code_change=True)
    store.evaluate("a", "mc", np.ones((3, 2)), fn)  # reused
    store.evaluate("b", "mc", np.zeros((2, 2)), fn)  # flown by the other code
    df = read_evals(tmp_path)
    assert df["code_changed"].tolist() == [False] * 3 + [True] * 2
    s = store.provenance_summary()
    assert s["rows_code_changed"] == 2 and sum(s["rows_used"].values()) == 5


def test_a_renamed_field_keeps_its_stored_name():
    """LoopConfig.family_config is stored as "family", so stores written before the rename
    keep their definition (and resume)."""
    from rvdjax.provenance import canonical
    from rvdjax.scenarios import SCENARIOS

    stored = canonical(SCENARIOS["thesis-vbar"].loop().config)
    assert "family" in stored and "family_config" not in stored
    assert stored["family"]["between_samples"] is True


def test_a_field_added_later_is_stored_only_away_from_its_old_behaviour():
    """Config.latch_turn (added after stores were flown) is left out of a definition while
    off, so the thesis' stored definitions still match; on, it is part of the definition."""
    import dataclasses

    from rvdjax.provenance import canonical, digest
    from rvdjax.scenarios import SCENARIOS

    cfg = SCENARIOS["thesis-vbar"].loop().config
    fam = canonical(cfg)["family"]
    assert "latch_turn" not in fam
    # the family record as it was stored before the field existed (the reference's store)
    assert fam == {"N": [30, 15, 12], "between_samples": True, "finite_burn": True,
                   "n_faces": 4, "rendezvous_cost": "qp"}  # fmt: skip
    on = dataclasses.replace(
        cfg, family_config=dataclasses.replace(cfg.family_config, latch_turn=True)
    )
    assert canonical(on)["family"]["latch_turn"] is True
    assert digest(on) != digest(cfg)


def test_the_plant_record_is_stored_as_the_parameters_own_fields():
    """Params.plant (rvdjax.loop.plant.Plant) is stored flat, as the fields were before the
    record, so definitions stored before it keep their digest: the nested parameters hash as
    a flat record of the same values built here by hand."""
    from collections import namedtuple

    from rvdjax.provenance import canonical, digest
    from rvdjax.scenarios import SCENARIOS

    params, _ = SCENARIOS["thesis-vbar"].build(thrusters=True)
    stored = canonical(params)
    assert "plant" not in stored
    assert {"mass", "orbit", "drag", "disturbances", "Ac", "Bc", "thrusters"} <= set(stored)
    names = [n for n in params._fields if n != "plant"] + list(params.plant._fields)
    Flat = namedtuple("Flat", names)
    flat = Flat(*[getattr(params, n) for n in params._fields if n != "plant"], *params.plant)
    assert digest(params) == digest(flat)
    # and the stored values are the plant's: another mass is another definition
    other = params._replace(plant=params.plant._replace(mass=params.plant.mass + 1.0))
    assert digest(other) != digest(params)


def test_every_benchmark_that_writes_json_records_its_provenance():
    """Each script under sweeps/ that writes JSON to a file stamps it with the code, the
    machine and its options (benchmark_block); a new benchmark without it fails here."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent / "sweeps"
    writes = re.compile(r"json\.dump\(|write_text\(json\.dumps|f\.write\(json\.dumps")
    writers = [p for p in sorted(root.glob("*.py")) if writes.search(p.read_text())]
    assert len(writers) >= 8
    assert [p.name for p in writers if "benchmark_block" not in p.read_text()] == []
    block = provenance.benchmark_block("sweeps/x.py", {"budget_s": 290.0, "handler": print})
    assert block["definition"] == {"benchmark": "sweeps/x.py", "options": {"budget_s": 290.0}}
