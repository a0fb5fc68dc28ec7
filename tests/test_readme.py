"""The README's Python example runs as written (it is the first code a user copies)."""

import pathlib
import re

import pytest

README = pathlib.Path(__file__).parents[1] / "README.md"


@pytest.mark.slow
def test_the_readme_python_example_runs(capsys):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    assert blocks, "the README has no Python example"
    exec(compile(blocks[0], "README.md", "exec"), {})
    first, second = capsys.readouterr().out.splitlines()[:2]
    docked, time_s, effort = first.split()
    assert docked == "True" and float(time_s) > 0 and float(effort) > 0
    assert 0.9 <= float(second.split()[0]) <= 1.0  # nearly every perturbed maneuver docks
