"""Every notebook (jupytext percent-format ``notebooks/*.py``) runs top to bottom as a script.

Each notebook runs in a fresh interpreter, not inside the test worker. Twice in about forty
suite runs on this project's 2-core machines (jax/jaxlib 0.10.2), XLA's CPU compiler killed a
long-lived test worker while a notebook compiled its programs (a segmentation fault while
writing the persistent cache, later an abort inside ``backend_compile_and_load``), and
pytest-xdist's ``loadfile`` scheduler then waited for the dead worker until CI's time ran out
(pytest-xdist issue 784). In a child process such a crash is one failed test with the child's
stderr in the report, and the notebook starts from the state a user's fresh kernel has.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parent.parent / "notebooks").glob("*.py"))
TIMEOUT_S = 900


def test_notebooks_exist():
    assert NOTEBOOKS, "no notebooks/*.py found"


def _run(path: Path, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, MPLBACKEND="Agg")  # any figure a notebook draws stays off screen
    return subprocess.run(
        [sys.executable, str(path)],
        cwd=cwd,  # files a notebook writes land in a scratch directory
        env=env,
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
    )


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path, tmp_path):
    proc = _run(path, tmp_path)
    if proc.returncode in (-signal.SIGSEGV, -signal.SIGABRT):
        # A signal from inside XLA's compiler, not a Python error of the notebook: run it once
        # more and say so. A notebook that raises, or crashes twice, fails.
        warnings.warn(
            f"{path.name}: the interpreter died with signal {-proc.returncode}; ran it again. "
            f"stderr tail:\n{proc.stderr[-2000:]}",
            stacklevel=1,
        )
        proc = _run(path, tmp_path)
    assert proc.returncode == 0, (
        f"{path.name} exited with {proc.returncode}\n--- stdout (tail) ---\n"
        f"{proc.stdout[-3000:]}\n--- stderr (tail) ---\n{proc.stderr[-6000:]}"
    )
