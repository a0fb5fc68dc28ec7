"""Verification of a guidance law: requirements as margins, dispersions as one standard-normal
vector, worst-case search and failure probabilities on the batch engine.

* :mod:`rvdjax.verify.requirements`: requirements as signed margins (exact and smooth);
* :mod:`rvdjax.verify.dispersions`: the dispersion vector xi ~ N(0, I) and its map to a run;
* :mod:`rvdjax.verify.evaluate`: batched exact and gradient evaluations;
* :mod:`rvdjax.verify.worst`: worst-case search (gradient, design point, baselines);
* :mod:`rvdjax.verify.probability`: subset simulation, importance sampling, Monte Carlo;
* :mod:`rvdjax.verify.subset`: subset simulation (adaptive conditional sampling, replicates);
* :mod:`rvdjax.verify.store`: the evaluations on disk (resume, replay, provenance).
"""

import importlib

__all__ = [
    "Composite",
    "Dispersion",
    "Problem",
    "ProblemSpec",
    "ProbabilitySpec",
    "Requirement",
    "SearchSpec",
    "estimate",
    "parse_dispersion",
    "parse_requirement",
    "problem_for",
    "search",
]

_WHERE = {
    "Composite": "requirements",
    "Requirement": "requirements",
    "parse_requirement": "requirements",
    "Dispersion": "dispersions",
    "parse_dispersion": "dispersions",
    "Problem": "evaluate",
    "ProblemSpec": "evaluate",
    "problem_for": "evaluate",
    "SearchSpec": "worst",
    "search": "worst",
    "ProbabilitySpec": "probability",
    "estimate": "probability",
}


def __getattr__(name):  # imported on first use: the command line starts without JAX
    if name in _WHERE:
        return getattr(importlib.import_module(f"rvdjax.verify.{_WHERE[name]}"), name)
    raise AttributeError(f"module 'rvdjax.verify' has no attribute {name!r}")
