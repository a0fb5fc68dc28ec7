"""Symmetric and triangular matrices stored as their lower triangles, row by row: the
factorisation's and the Newton blocks' storage between the kernels."""

from __future__ import annotations

import math

import jax.numpy as jnp


def tri_size(n: int) -> int:
    """Entries of an n x n symmetric (or triangular) matrix's lower triangle."""
    return n * (n + 1) // 2


def pack(L, P):
    """The kernels' storage of a factorisation from (L, P), batch last (L (N, nu,
    nu, b), P (N, nx, nx, b)): L's and P's lower triangles, row by row ((N, tri(nu), b),
    (N, tri(nx), b); :func:`tri_pack`). P is symmetric and L's upper
    triangle zero, so nothing is lost; the solves read 21 entries of P a stage instead of 36
    (P's upper triangle was about a quarter of an accurate iteration's reads of the
    factorisation: docs/benchmark.md)."""
    return tri_pack(L, 1), tri_pack(P, 1)


def unpack(L, P):
    """(L, P) as full matrices, batch last, from :func:`pack`'s storage (L's upper
    triangle 0, P mirrored)."""
    return tri_unpack(L, 1, False), tri_unpack(P, 1, True)


def _tri_pairs(n):
    return [(i, j) for i in range(n) for j in range(i + 1)]


def tri_pack(X, axis: int = -2):
    """The lower triangle, row by row, of the n x n matrices whose axes are ``axis`` and the
    next: one axis of n (n + 1) / 2 entries in their place."""
    axis = axis % X.ndim
    flat = jnp.stack([X[(slice(None),) * axis + (i, j)] for i, j in _tri_pairs(X.shape[axis])])
    return jnp.moveaxis(flat, 0, axis)


def tri_unpack(flat, axis: int, symmetric: bool):
    """The matrices of :func:`tri_pack`'s triangles at ``axis``: mirrored (``symmetric``) or
    with a zero upper triangle."""
    axis = axis % flat.ndim
    n = (math.isqrt(8 * flat.shape[axis] + 1) - 1) // 2
    at = {ij: k for k, ij in enumerate(_tri_pairs(n))}
    entries = jnp.moveaxis(flat, axis, 0)
    zero = jnp.zeros_like(entries[0])

    def entry(i, j):
        if (i, j) in at:
            return entries[at[(i, j)]]
        return entries[at[(j, i)]] if symmetric else zero

    rows = jnp.stack([jnp.stack([entry(i, j) for j in range(n)]) for i in range(n)])
    return jnp.moveaxis(rows, (0, 1), (axis, axis + 1))
