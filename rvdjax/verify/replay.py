"""One run of a stored verification, made flyable again (``rvdjax run SCENARIO --study DIR
--run R``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["KIND", "replay", "is_verification"]

#: The key of a verification directory's config.json that names its command.
KIND = "verify"


def replay(out, run: int):
    """(spec, flight) of run ``run`` of the verification in ``out``: the
    :class:`~rvdjax.scenarios.flight.Flight` with that run's dispersed parameters and
    initial state."""
    from rvdjax.verify.evaluate import Problem, ProblemSpec
    from rvdjax.verify.store import CONFIG, read_evals

    config = json.loads((Path(out) / CONFIG).read_text())
    pspec = ProblemSpec(**config["spec"])
    df = read_evals(out)
    row = df[df["run"] == run]
    if row.empty:
        raise ValueError(f"run must be one of the runs in {out} (0 .. {int(df['run'].max())})")
    xi = np.asarray(row["xi"].iloc[0], float)
    pb = Problem(pspec)
    x0, params = pb.dispersion.apply(xi, pb.x0, pb.params, pb.scenario.guidance_family.layout)
    return pspec, pb.flight.replace(params=params, x0=x0, solver_params=pb.sp)


def is_verification(out) -> bool:
    """``out`` holds a verification (``rvdjax verify``), not a study."""
    from rvdjax.verify.store import CONFIG

    p = Path(out) / CONFIG
    return p.exists() and KIND in json.loads(p.read_text())
