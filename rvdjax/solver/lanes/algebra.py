"""Small-matrix algebra over lane vectors, entry by entry (no ``dot``: float64 MMA needs
blocks of 16 and more): the arithmetic of every Riccati and row kernel.

A matrix is a list of rows, each a list of entries; an entry is anything that broadcasts
(a lane vector, a scalar of a shared model, a traced array with trailing batch axes). Sums
run left to right from 0, as the elementwise products of :mod:`rvdjax.solver.riccati` do."""

from __future__ import annotations

import jax.numpy as jnp


def _dot(xs, ys):
    return sum(x * y for x, y in zip(xs, ys, strict=True))


def _col(X, j):
    return [row[j] for row in X]


def _mm(X, Y):
    """X @ Y."""
    cols = [_col(Y, j) for j in range(len(Y[0]))]
    return [[_dot(row, c) for c in cols] for row in X]


def _mtm(X, Y):
    """X^T @ Y."""
    return [[_dot(_col(X, i), _col(Y, j)) for j in range(len(Y[0]))] for i in range(len(X[0]))]


def _mv(X, v):
    return [_dot(row, v) for row in X]


def _mtv(X, v):
    return [_dot(_col(X, j), v) for j in range(len(X[0]))]


def _add(X, Y):
    return [[x + y for x, y in zip(rx, ry, strict=True)] for rx, ry in zip(X, Y, strict=True)]


def _sym(X):
    n = len(X)
    return [[0.5 * (X[i][j] + X[j][i]) for j in range(n)] for i in range(n)]


def chol(H):
    """Lower Cholesky factor of a small SPD matrix (lists), entry by entry; NaN if H is not
    positive definite. The upper triangle is None."""
    n = len(H)
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        d = jnp.sqrt(H[j][j] - sum(L[j][k] * L[j][k] for k in range(j)))
        L[j][j] = d
        for i in range(j + 1, n):
            L[i][j] = (H[i][j] - sum(L[i][k] * L[j][k] for k in range(j))) / d
    return L


def chol_solve(L, b):
    """x with (L L^T) x = b for a lower factor from :func:`chol` and a vector b (list)."""
    n = len(L)
    y = []
    for i in range(n):
        y.append((b[i] - sum(L[i][k] * y[k] for k in range(i))) / L[i][i])
    x = [None] * n
    for i in reversed(range(n)):
        x[i] = (y[i] - sum(L[k][i] * x[k] for k in range(i + 1, n))) / L[i][i]
    return x


def _chol_solve_mat(L, Bm):
    """X with (L L^T) X = Bm, column by column."""
    cols = [chol_solve(L, _col(Bm, j)) for j in range(len(Bm[0]))]
    return [[c[i] for c in cols] for i in range(len(L))]
