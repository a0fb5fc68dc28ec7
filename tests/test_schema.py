"""Each family's physical inputs are declared once (rvdjax.schema): make_params' signature and
checks, the scenario files' [physical] keys and kinds, the study names and the docs tables."""

from __future__ import annotations

import inspect
import subprocess
import sys

import pytest

from rvdjax.families import FAMILIES, tables
from rvdjax.scenarios import SCENARIOS
from rvdjax.scenarios.files import _physical_schema
from rvdjax.schema import REQUIRED, Input, Schema


def test_docs_tables_are_up_to_date():
    text = tables.DOC.read_text()
    assert tables.update(text) == text, "run `python -m rvdjax.families.tables`"


@pytest.mark.parametrize("name", list(FAMILIES))
def test_signature_and_toml_keys_come_from_the_schema(name):
    fam = FAMILIES[name]
    params = inspect.signature(fam.make_params).parameters
    assert tuple(params) == fam.schema.names
    for i in fam.schema:
        default = params[i.name].default
        assert (default is inspect.Parameter.empty) == (i.default is REQUIRED)
    kinds, required = _physical_schema(fam)
    assert "x0" not in kinds and set(required) <= set(kinds)


def test_every_builtin_scenario_names_only_schema_inputs():
    for sc in SCENARIOS.values():
        assert set(sc.physical) <= set(sc.guidance_family.schema.names), sc.name


def test_unknown_and_missing_inputs_are_type_errors():
    make = FAMILIES["rendezvous"].make_params
    with pytest.raises(TypeError, match="unexpected keyword argument 'masss'"):
        make(masss=1.0)
    with pytest.raises(TypeError, match="missing .* required keyword-only argument"):
        make(mass=1.0)


def test_checks_name_the_input_and_the_range():
    schema = Schema(
        (
            Input("a", "a length", "m", check="positive"),
            Input("k", "a count", kind="int", check="choice", choices=(1, 2), default=1),
            Input("w", "weights", shape="per-phase", check="nonnegative", default=(0.0, 1.0)),
        ),
        n_phases=2,
    )
    schema.check({"a": 1.0, "k": 2, "w": (0.0, 3.0)})
    with pytest.raises(ValueError, match=r"^a must be finite and in \(0, inf\) m, got -1.0$"):
        schema.check({"a": -1.0, "k": 1, "w": (0.0, 1.0)})
    with pytest.raises(ValueError, match=r"k must be one of \(1, 2\)"):
        schema.check({"a": 1.0, "k": 3, "w": (0.0, 1.0)})
    with pytest.raises(ValueError, match="one value per phase"):
        schema.check({"a": 1.0, "k": 1, "w": (0.0,)})
    assert "| `a` | () | m | > 0 | required | a length |" in schema.markdown()


def test_study_aliases_from_the_schema():
    from rvdjax.study.spec import aliases

    short = aliases("three-phase")
    assert short["Ts2"] == "ts[1]" and short["N3"] == "N[2]"
    assert aliases("rendezvous") == {}


def test_importing_the_families_imports_no_matplotlib():
    code = (
        "import sys, importlib, pkgutil, rvdjax.families as f\n"
        "for m in pkgutil.iter_modules(f.__path__):\n"
        "    importlib.import_module('rvdjax.families.' + m.name)\n"
        "import rvdjax.loop, rvdjax.scenarios\n"
        "rvdjax.scenarios.SCENARIOS['fastmpc-3d']\n"
        "assert 'matplotlib' not in sys.modules, 'matplotlib imported'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
