"""pyproject.toml's minimum versions are the ones the suite was run with (.ci/floor.txt)."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TESTED_EXTRAS = ("test", "peers", "nmpc")  # the README's test command installs these
# ruff lints in CI with its newest release (its rules and format move between releases); the
# suite does not run it, so the floor does not pin it
UNPINNED = {"ruff"}


def _minimums() -> dict[str, str]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    reqs = list(project["dependencies"])
    for extra in TESTED_EXTRAS:
        reqs += project["optional-dependencies"][extra]
    out = {}
    for req in reqs:
        m = re.fullmatch(r"([A-Za-z0-9_.-]+)(?:\[[^]]*\])?>=([0-9][0-9A-Za-z.]*)", req.strip())
        assert m, f"pyproject.toml: {req!r} is not 'name>=version'"
        out[m.group(1).lower()] = m.group(2)
    return out


def _floor() -> dict[str, str]:
    out = {}
    for line in (ROOT / ".ci" / "floor.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, version = line.split("==")
            out[name.lower()] = version
    return out


def test_the_minimum_versions_are_the_tested_floor():
    minimums, floor = _minimums(), _floor()
    untested = {n: v for n, v in minimums.items() if n not in UNPINNED and floor.get(n) != v}
    assert not untested, f"minimums not in .ci/floor.txt as tested: {untested}"
    # jaxlib is jax's own dependency, pinned with it; nothing else in the floor is unlisted
    assert floor.pop("jaxlib") == floor["jax"]
    assert set(floor) == set(minimums) - UNPINNED
