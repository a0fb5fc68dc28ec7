"""Constraint blocks: the rows ``F v <= f`` of one kind (hard, penalty, monitor), stacked into
an OCP, chosen among alternatives, and their margins (the package docstring)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["Block", "stack", "exclusive", "margins", "block_margin", "hard_mask"]


KINDS = ("hard", "penalty", "monitor")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Block:
    """Named stage-wise rows ``F[t] @ v <= f[t]`` (module docstring).

    Attributes:
        F: (N, m, n) row normals acting on x_{t+1} (n = nx) or u_t (n = nu).
        f: (N, m) offsets.
        rho: (N, m) exact-penalty weight of soft state rows [cost per unit of violation].
        mask: (N, m) 1.0 where a row is active, 0.0 where it is switched off.
        name: static name (the key of the block's margin in the loop's records).
        kind: static "hard", "penalty" or "monitor".
        acts_on: static "x" or "u".
        hard: (N, m) 1.0 on "hard" rows, where hardness differs from row to row (blocks made
            by :func:`exclusive`); None: every row is of ``kind``.
    """

    F: jnp.ndarray
    f: jnp.ndarray
    rho: jnp.ndarray
    mask: jnp.ndarray
    hard: jnp.ndarray | None = None
    name: str = dataclasses.field(default="rows", metadata=dict(static=True))
    kind: str = dataclasses.field(default="hard", metadata=dict(static=True))
    acts_on: str = dataclasses.field(default="x", metadata=dict(static=True))

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {self.kind!r}")
        if self.acts_on not in ("x", "u"):
            raise ValueError(f"acts_on must be 'x' or 'u', got {self.acts_on!r}")

    @property
    def N(self) -> int:
        return self.F.shape[-3]

    @property
    def m(self) -> int:
        return self.F.shape[-2]

    def masked(self, on) -> Block:
        """The block with its mask multiplied by ``on`` (scalar, (N,) per stage or (N, m))."""
        on = jnp.asarray(on, self.mask.dtype)
        if on.ndim == 1:
            on = on[:, None]
        return dataclasses.replace(self, mask=self.mask * on)

    def with_(self, **changes) -> Block:
        return dataclasses.replace(self, **changes)


def _block(F, f, name, kind="hard", acts_on="x", rho=1.0, mask=1.0) -> Block:
    F = jnp.asarray(F)
    f = jnp.asarray(f)
    dtype = f.dtype
    return Block(
        F=F,
        f=f,
        rho=jnp.broadcast_to(jnp.asarray(rho, dtype), f.shape),
        mask=jnp.broadcast_to(jnp.asarray(mask, dtype), f.shape),
        name=name,
        kind=kind,
        acts_on=acts_on,
    )


def stack(blocks: Sequence[Block]):
    """Concatenate blocks along the row axis: (F, f, rho, mask) for the OCP's ``Fx, fx, rho,
    x_mask`` (state blocks) or ``Fu, fu, -, u_mask`` (input blocks)."""
    if not blocks:
        raise ValueError("stack needs at least one block")
    sides = {b.acts_on for b in blocks}
    if len(sides) != 1:
        raise ValueError("stack state blocks and input blocks separately")
    cat = lambda a: jnp.concatenate(a, axis=1)  # noqa: E731
    return (
        cat([b.F for b in blocks]),
        cat([b.f for b in blocks]),
        cat([b.rho for b in blocks]),
        cat([b.mask for b in blocks]),
    )


def _hard_rows(b: Block):
    if b.hard is not None:
        return b.hard
    return jnp.full(b.mask.shape, 1.0 if b.kind == "hard" else 0.0, b.mask.dtype)


def hard_mask(blocks: Sequence[Block]):
    """(N, m) 1.0 on the active rows of the "hard" blocks, in :func:`stack` order."""
    return jnp.concatenate([b.mask * _hard_rows(b) for b in blocks], axis=1)


def exclusive(alternatives: Sequence[Sequence[Block]], index, name: str = "exclusive") -> Block:
    """One block carrying the stacked rows of ``alternatives[index]`` (``index`` may be traced).

    Sets of blocks that are never active together (the phases of a phased guidance) share
    rows instead of being stacked one after the other: the OCP carries the largest set's
    count of rows rather than the sum, and the solver's work on the state rows grows with that
    count. Rows past the chosen set's own count are padding (mask 0). Hardness is kept per row
    (``Block.hard``), so :func:`hard_mask` still marks the chosen set's "hard" rows; ``kind``
    of the result is only a label.
    """
    if not alternatives or any(len(alt) == 0 for alt in alternatives):
        raise ValueError("exclusive needs at least one block in every alternative")
    sides = {b.acts_on for alt in alternatives for b in alt}
    if len(sides) != 1:
        raise ValueError("exclusive takes state blocks or input blocks, not both")
    parts = [
        (*stack(alt), jnp.concatenate([_hard_rows(b) for b in alt], axis=1)) for alt in alternatives
    ]
    m = max(p[0].shape[1] for p in parts)

    def pad(a, value):
        widths = [(0, 0)] * a.ndim
        widths[1] = (0, m - a.shape[1])
        return jnp.pad(a, widths, constant_values=value)

    # padding rows: zero normal, unit offset and penalty, inactive (as the solver neutralises)
    fill = (0.0, 1.0, 1.0, 0.0, 0.0)  # F, f, rho, mask, hard
    padded = [tuple(pad(a, v) for a, v in zip(p, fill, strict=True)) for p in parts]

    def pick(k):
        return jnp.stack([p[k] for p in padded])[index]

    return Block(
        F=pick(0),
        f=pick(1),
        rho=pick(2),
        mask=pick(3),
        hard=pick(4),
        name=name,
        kind="hard",
        acts_on=sides.pop(),
    )


def block_margin(block: Block, v):
    """(N, m) row slacks ``f - F v`` of one block at ``v`` ((nx,) or stage-wise (N, nx)),
    +inf on inactive rows. Rows have unit normals: a slack is a distance (negative inside)."""
    v = jnp.asarray(v)
    Fv = (
        jnp.einsum("tij,j->ti", block.F, v) if v.ndim == 1 else jnp.einsum("tij,tj->ti", block.F, v)
    )
    return jnp.where(block.mask > 0, block.f - Fv, jnp.inf)


def margins(blocks: Sequence[Block], v) -> dict:
    """{name: (m,) per-row slack at the first stage} of single-stage blocks (the truth's
    margins at one instant, blocks built with N = 1)."""
    return {b.name: block_margin(b, v)[0] for b in blocks}


# --------------------------------------------------------------------------- helpers


def _concrete(x) -> bool:
    """True when ``x`` holds concrete values (not a JAX tracer) and can be range-checked."""
    if isinstance(x, jax.core.Tracer):
        return False
    if isinstance(x, (list, tuple)):
        return all(_concrete(v) for v in x)
    return True


def _check(name: str, x, lo=None, hi=None, lo_open=True, hi_open=True) -> None:
    """Raise ValueError unless every entry of concrete ``x`` is finite and within (lo, hi)."""
    if x is None or not _concrete(x):
        return
    a = np.asarray(x, dtype=float)
    ok = np.all(np.isfinite(a))
    if lo is not None:
        ok = ok and np.all(a > lo if lo_open else a >= lo)
    if hi is not None:
        ok = ok and np.all(a < hi if hi_open else a <= hi)
    if not ok:
        lb = "-inf" if lo is None else f"{lo:g}"
        ub = "inf" if hi is None else f"{hi:g}"
        rng = f"{'(' if lo_open else '['}{lb}, {ub}{')' if hi_open else ']'}"
        raise ValueError(f"{name} must be finite and in {rng}, got {x!r}")


def _check_index(name: str, index, nx: int) -> tuple[int, ...]:
    index = tuple(int(i) for i in index)
    if not index or any(i < 0 or i >= nx for i in index) or len(set(index)) != len(index):
        raise ValueError(f"{name} must be distinct ints in [0, {nx}), got {index!r}")
    return index


def _pos_index(pos_index, d: int, nx: int) -> tuple[int, ...]:
    if not isinstance(nx, (int, np.integer)) or nx < d:
        raise ValueError(f"nx (state dimension) must be an int >= {d}, got {nx!r}")
    idx = tuple(range(d)) if pos_index is None else pos_index
    idx = _check_index("pos_index", idx, nx)
    if len(idx) != d:
        raise ValueError(f"pos_index must have {d} entries (position dimension), got {idx!r}")
    return idx


def _embed(a, nx: int, index: tuple[int, ...]):
    """Scatter the last axis of ``a`` (len(index)) into state columns ``index`` of width nx."""
    a = jnp.asarray(a)
    return jnp.zeros((*a.shape[:-1], nx), a.dtype).at[..., jnp.array(index)].set(a)


def _unit2(angle):
    angle = jnp.asarray(angle, dtype=float)
    return jnp.stack([jnp.cos(angle), jnp.sin(angle)], axis=-1)


def _safe_normalise(v, fallback):
    n2 = jnp.sum(v * v, axis=-1, keepdims=True)
    ok = n2 > 1e-24
    return jnp.where(ok, v / jnp.sqrt(jnp.where(ok, n2, 1.0)), fallback)


def _wrap(a):
    """Wrap angles to [-pi, pi)."""
    return (a + jnp.pi) % (2 * jnp.pi) - jnp.pi
