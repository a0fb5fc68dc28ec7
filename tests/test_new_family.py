"""The family of docs/writing-a-family.md (docs/examples/double_integrator.py) flies in closed
loop: a few MPC steps, a short horizon."""

from __future__ import annotations

import importlib.util
import pathlib
import sys

import numpy as np
import pytest

from rvdjax.loop import Loop, LoopConfig, fly

PATH = pathlib.Path(__file__).resolve().parents[1] / "docs" / "examples" / "double_integrator.py"


def _module():
    spec = importlib.util.spec_from_file_location("double_integrator", PATH)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look the module up
    spec.loader.exec_module(mod)
    return mod


DI = _module()


def test_the_guide_family_flies_to_the_origin():
    params = DI.make_params(u_max=0.5)
    loop = Loop(DI.FAMILY, LoopConfig(family_config=DI.Config(N=8), n_steps=30))
    x0 = np.array([2.0, 0.0])
    infos, m = fly(loop, params, x0)
    active = np.asarray(infos.active)
    assert np.all(np.abs(np.asarray(infos.u)[active]) <= 0.5 + 1e-6)  # the thrust bound holds
    assert bool(m.docked)  # within arrive_tol of the origin
    assert 0 < int(m.steps) < 30


def test_the_guide_family_checks_its_inputs():
    with pytest.raises(ValueError, match=r"u_max must be finite and in \(0, inf\) N"):
        DI.make_params(u_max=-1.0)
    assert DI.FAMILY.schema.names[:3] == ("mass", "ts", "u_max")


def test_a_family_without_a_plant_is_refused_when_traced():
    """The kernel reads only params.plant: parameters without a Plant are refused by name."""
    from typing import NamedTuple

    from rvdjax.loop.kernel import init

    params = DI.make_params()

    class NoPlant(NamedTuple):
        A: object
        mass: object

    loop = Loop(DI.FAMILY, LoopConfig(family_config=DI.Config(N=8), n_steps=3))
    with pytest.raises(TypeError, match=r"need a field plant: rvdjax\.loop\.plant\.Plant"):
        init(loop, NoPlant(params.A, params.plant.mass), np.zeros(2))
