"""Every notebook (jupytext percent-format ``notebooks/*.py``) runs top to bottom as a script."""

from __future__ import annotations

import runpy
from pathlib import Path

import matplotlib
import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parent.parent / "notebooks").glob("*.py"))


def test_notebooks_exist():
    assert NOTEBOOKS, "no notebooks/*.py found"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path, monkeypatch, tmp_path):
    matplotlib.use("Agg")  # any figure a notebook draws stays off screen
    monkeypatch.chdir(tmp_path)  # files a notebook writes land in a scratch directory
    runpy.run_path(str(path), run_name="__main__")
