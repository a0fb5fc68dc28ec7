"""Array layouts of one primal-dual iteration: one problem, or a batch kept on the last axis.

The algebra of an iteration (:mod:`rvdjax.solver.primal_dual`) needs a few stage-wise
products and per-problem reductions. :data:`ONE` computes them for one problem (the arrays of
:class:`~rvdjax.ocp.OCP` as documented: stage axis first, no batch axis): einsum products and
reductions over every axis. Under ``vmap`` that layout keeps the batch first, so every
6 x 6 product and every reduction over a 6-long row runs one problem at a time.

:data:`BATCH_LAST` computes the same quantities on arrays that carry one *trailing* batch axis
(size B, or 1 for data shared by the whole batch): each product is a broadcast multiply and a
sum over a leading axis, each reduction runs over every axis but the last, so every operation
is a vector operation over the batch (the layout of the Riccati recursion's elementwise form,
:mod:`rvdjax.solver.kkt`). A per-problem scalar is a (B,) array, which broadcasts against the
trailing axis of every (..., B) array: the iteration's code is the same in both layouts.
:func:`to_last` / :func:`to_first` move a batched pytree in and out of that layout.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

__all__ = ["Layout", "ONE", "BATCH_LAST", "to_last", "to_first", "shared_to_last"]


class Layout(NamedTuple):
    """Stage-wise products and per-problem reductions of one array layout.

    Attributes:
        mv: (F (t, i, j), v (t, j)) -> F_t v_t, (t, i).
        mtv: (F (t, i, j), w (t, i)) -> F_t^T w_t, (t, j).
        gram: (F (t, k, i), d (t, k)) -> F_t^T diag(d_t) F_t, (t, i, j).
        total, largest, smallest, every: sum, max, min, all of one problem's entries.
    """

    mv: Callable
    mtv: Callable
    gram: Callable
    total: Callable
    largest: Callable
    smallest: Callable
    every: Callable


def _over_problem(reduce):
    """``reduce`` over every axis but the trailing batch axis."""
    return lambda a: reduce(a, axis=tuple(range(a.ndim - 1)))


ONE = Layout(
    mv=lambda F, v: jnp.einsum("tij,tj->ti", F, v),
    mtv=lambda F, w: jnp.einsum("tij,ti->tj", F, w),
    gram=lambda F, d: jnp.einsum("tki,tk,tkj->tij", F, d, F),
    total=jnp.sum,
    largest=jnp.max,
    smallest=jnp.min,
    every=jnp.all,
)

# Index leading axes only, so that the trailing batch axis rides along in every operation.
BATCH_LAST = Layout(
    mv=lambda F, v: jnp.sum(F * v[:, None], axis=2),
    mtv=lambda F, w: jnp.sum(F * w[:, :, None], axis=1),
    gram=lambda F, d: jnp.sum(F[:, :, :, None] * (d[:, :, None, None] * F[:, :, None]), axis=1),
    total=_over_problem(jnp.sum),
    largest=_over_problem(jnp.max),
    smallest=_over_problem(jnp.min),
    every=_over_problem(jnp.all),
)


def to_last(tree):
    """A pytree with a leading batch axis on every leaf -> the batch axis last."""
    return jax.tree.map(lambda a: jnp.moveaxis(a, 0, -1), tree)


def to_first(tree):
    """Inverse of :func:`to_last`."""
    return jax.tree.map(lambda a: jnp.moveaxis(a, -1, 0), tree)


def shared_to_last(tree):
    """Data shared by a whole batch (no batch axis) -> a trailing axis of size 1."""
    return jax.tree.map(lambda a: jnp.asarray(a)[..., None], tree)
