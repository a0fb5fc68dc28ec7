"""Shared closed-loop flights for the tests: one compiled program per loop configuration,
and one flight per (scenarios, mode, options), reused by every test file that asks for it."""

from __future__ import annotations

import functools

import jax
import numpy as np

from rvdjax.loop import fly
from rvdjax.scenarios import SCENARIOS


@functools.cache
def flyer(loop):
    """jit(vmap(fly)) over (params, x0, key) with shared solver parameters."""
    return jax.jit(jax.vmap(lambda p, x, k, s: fly(loop, p, x, k, s), in_axes=(0, 0, 0, None)))


def stack(trees):
    return jax.tree.map(lambda *a: np.stack([np.asarray(x) for x in a]), *trees)


@functools.cache
def flight(names: tuple[str, ...], mode: str = "accurate", seeds=None, **loop_kw):
    """Fly scenarios that share one loop (same family and static configuration) as one
    vmapped batch. Returns (loop, params, infos, metrics), NumPy, leading axis = scenario."""
    scs = [SCENARIOS[n] for n in names]
    loops = {sc.loop(mode, **loop_kw) for sc in scs}
    assert len(loops) == 1, f"{names} do not share one loop"
    loop = loops.pop()
    kappas = {sc.paper_kappa for sc in scs}
    assert len(kappas) == 1 or mode != "paper", "one paper-mode kappa per batch"
    built = [sc.build() for sc in scs]
    params = stack([b[0] for b in built])
    x0 = np.stack([b[1] for b in built])
    seeds = seeds or tuple(range(len(names)))
    keys = jax.vmap(jax.random.key)(np.asarray(seeds))
    infos, m = flyer(loop)(params, x0, keys, scs[0].solver_params(mode))
    return loop, params, jax.tree.map(np.asarray, infos), jax.tree.map(np.asarray, m)


def first(tree, i=0):
    """Element i of a batched pytree."""
    return jax.tree.map(lambda a: np.asarray(a)[i], tree)
