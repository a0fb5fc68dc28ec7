"""XLA CPU compiler options that rvdjax sets when it is imported.

rvdjax's arrays are small blocks (3-9 wide, a horizon of 15-60 stages) batched over slots.
Three of XLA's CPU defaults slow them down (measured in docs/benchmark.md, "XLA's CPU
options"):

- ``--xla_cpu_experimental_ynn_fusion_type=`` (empty: no YNNPACK fusions). jaxlib >= 0.9
  hands small dot-like products (e.g. a stage's P [B A] with the model shared by a chunk of
  slots) to YNNPACK, a library call per product and stage whose cost dwarfs the arithmetic
  at these sizes; with the option off, XLA emits the loops itself.
- ``--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=100000000``. XLA
  runs a ``while`` loop (every ``lax.scan`` over stages) by dispatching each fused kernel of
  its body in turn, a few dozen per Riccati stage; a loop whose buffers are below the
  threshold is compiled into one function instead. 100 MB hoists every loop rvdjax runs.
  The hoisted code contracts multiplies and adds into FMAs in other places than the
  dispatched kernels do, which moved the last bits of the Riccati recursion's triangular
  solves; the solver is written to be insensitive to that (:mod:`rvdjax.solver.riccati`).
- ``--xla_cpu_prefer_vector_width=512``, on CPUs with AVX-512 only. LLVM's default for x86
  is 256-bit vectors; a chunk's arrays carry 32 slots on their last axis, four 512-bit
  vectors of float64.

Not set, although faster still: ``--xla_cpu_use_fusion_emitters=false`` (XLA's older loop
emitters) made the accurate-mode solver return NONFINITE on two random test problems that
it solves with the default emitters (tests/test_solver.py, shape classes "large" and
"long", seed 0; jaxlib 0.10.2).

XLA reads ``XLA_FLAGS`` once, when JAX creates its CPU backend, so the options are added at
import, before any computation. They go in front of the user's flags: XLA stops reading at
the first token that is not an option (the folklore ``intra_op_parallelism_threads=1`` is
one; rvdjax warns about it), and options after it are silently dropped. Options the user set
(to any value) are left alone, and
``RVDJAX_XLA_OPTIONS=0`` keeps ``XLA_FLAGS`` untouched. An option is added only for jaxlib
versions known to have it (XLA aborts on an unknown flag). If JAX already ran a computation
before rvdjax was imported, nothing can be changed: a warning says so.
"""

from __future__ import annotations

import os
import warnings

__all__ = [
    "AVX512_OPTIONS",
    "OPTIONS",
    "OPT_OUT",
    "apply",
    "has_avx512",
    "stray_tokens",
    "wanted",
]

# (option, first jaxlib version that has it: checked in the released wheels)
OPTIONS = (
    ("--xla_cpu_experimental_ynn_fusion_type=", (0, 9)),
    ("--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=100000000", (0, 10)),
)
AVX512_OPTIONS = (("--xla_cpu_prefer_vector_width=512", (0, 10)),)
OPT_OUT = "RVDJAX_XLA_OPTIONS"


def _version(text: str) -> tuple[int, ...]:
    parts = []
    for p in text.split(".")[:2]:
        digits = "".join(c for c in p if c.isdigit())
        parts.append(int(digits) if digits else 0)
    return tuple(parts)


def wanted(xla_flags: str, jaxlib_version: str, avx512: bool = False) -> list[str]:
    """The options to append to ``xla_flags`` for this jaxlib (and CPU): those it has and the
    user has not set."""
    have = _version(jaxlib_version)
    options = OPTIONS + (AVX512_OPTIONS if avx512 else ())
    return [
        opt for opt, since in options if have >= since and opt.split("=")[0] + "=" not in xla_flags
    ]


def stray_tokens(xla_flags: str) -> list[str]:
    """The tokens of ``xla_flags`` that are not ``--options``: XLA stops reading there."""
    return [t for t in xla_flags.split() if not t.startswith("--")]


def has_avx512() -> bool:
    """The CPU has AVX-512F (Linux: /proc/cpuinfo; elsewhere assumed not)."""
    try:
        with open("/proc/cpuinfo") as f:
            return any(line.startswith("flags") and " avx512f" in line for line in f)
    except OSError:
        return False


def _backend_started() -> bool:
    """JAX has created a backend (XLA_FLAGS already read). JAX has no public test for it; its
    public ``get_backend`` is a cache, filled when the first backend is made. If a JAX version
    changes that, assume not (the options are then appended, at worst without effect)."""
    try:
        from jax.extend.backend import get_backend

        return get_backend.cache_info().currsize > 0
    except (ImportError, AttributeError):
        return False


def apply() -> list[str]:
    """Append the options to ``XLA_FLAGS`` (see the module docstring); returns those added."""
    if os.environ.get(OPT_OUT, "1").strip().lower() in ("0", "false", "no", "off"):
        return []
    import jaxlib.version

    current = os.environ.get("XLA_FLAGS", "")
    stray = stray_tokens(current)
    if stray:
        warnings.warn(
            f"XLA_FLAGS holds {' '.join(stray)!r}, which is not an XLA option: XLA ignores "
            "everything from there on (rvdjax puts its own options first).",
            stacklevel=3,
        )
    add = wanted(current, jaxlib.version.__version__, has_avx512())
    if not add:
        return []
    if _backend_started():
        warnings.warn(
            "rvdjax was imported after JAX had started its backend, so its XLA CPU options "
            f"({' '.join(add)}) are not in effect: batches run slower. Import "
            "rvdjax before running any JAX computation, or put them in XLA_FLAGS "
            f"(set {OPT_OUT}=0 to silence this).",
            stacklevel=3,
        )
        return []
    os.environ["XLA_FLAGS"] = " ".join([*add, current]).strip()
    return add


def one_thread() -> None:
    """Keep XLA's CPU backend off Eigen's thread pool (must run before JAX first computes).

    Only real XLA options go into ``XLA_FLAGS``: XLA stops reading the variable at the first
    token it does not know (the folklore ``intra_op_parallelism_threads=1`` is one), so
    everything after it, rvdjax's own options included, would silently be dropped. For
    single-core timings pin the process as well (``taskset -c 0``)."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "--xla_cpu_multi_thread_eigen=" not in flags:
        os.environ["XLA_FLAGS"] = (flags + " --xla_cpu_multi_thread_eigen=false").strip()
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def host_devices(count: int) -> None:
    """On a CPU, one XLA host device per core asked for (``--devices N``; before JAX starts);
    a count the user already set in ``XLA_FLAGS`` is kept."""
    flags = os.environ.get("XLA_FLAGS", "")
    if count > 1 and "xla_force_host_platform_device_count" not in flags:
        os.environ["XLA_FLAGS"] = (
            f"--xla_force_host_platform_device_count={count} " + flags
        ).strip()
