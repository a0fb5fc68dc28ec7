"""Batch studies (paper 003 Chapters 4-6): Monte Carlo over initial conditions, parameters
and disturbances, sweeps over horizons and sample times, resumable tidy tables, statistics.

:mod:`.samplers` (initial conditions and distributions from JAX keys), :mod:`.spec` (a study
as data), :mod:`.runner` (the batch engine, writing as it goes), :mod:`.table` (Parquet parts),
:mod:`.stats` (Clopper-Pearson, zero-failure rule, percentiles), :mod:`.report` (summaries),
:mod:`.figures` (the paper's plots from a table).
"""

from rvdjax.study.report import format_summary, summarize
from rvdjax.study.runner import replay, run_study
from rvdjax.study.spec import StudySpec
from rvdjax.study.table import read_table

__all__ = ["StudySpec", "run_study", "summarize", "format_summary", "read_table", "replay"]
