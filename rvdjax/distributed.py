"""Several processes flying one study (``jax.distributed``): start and synchronise them.

The study's runs are split by process index (:func:`rvdjax.study.run_study`); these helpers
only start JAX's coordination and wait for every process, through JAX's public API."""

from __future__ import annotations

__all__ = ["initialize", "barrier", "shutdown"]


def initialize(
    coordinator: str | None,
    num_processes: int | None = None,
    process_id: int | None = None,
    timeout_s: int = 120,
) -> tuple[int, int]:
    """(process index, process count). ``coordinator`` None: one process, nothing started;
    "auto": JAX reads the cluster's environment (Slurm's ``srun``, Open MPI, ...); else the
    coordinator's HOST:PORT with ``num_processes`` and ``process_id``. Must run before anything
    else touches JAX."""
    if not coordinator:
        return 0, 1
    import jax

    if coordinator == "auto":
        jax.distributed.initialize(initialization_timeout=timeout_s)
        return jax.process_index(), jax.process_count()
    if num_processes is None or process_id is None:
        raise ValueError("coordinator HOST:PORT needs num_processes and process_id")
    jax.distributed.initialize(
        coordinator_address=coordinator,
        num_processes=num_processes,
        process_id=process_id,
        initialization_timeout=timeout_s,
    )
    return jax.process_index(), jax.process_count()


def barrier(name: str, count: int) -> None:
    """Wait until every one of the ``count`` processes reaches the barrier ``name`` (a
    collective over every process's devices; nothing to do for one process)."""
    if count == 1:
        return
    from jax.experimental import multihost_utils

    multihost_utils.sync_global_devices(name)


def shutdown(count: int) -> None:
    if count > 1:
        import jax

        jax.distributed.shutdown()
