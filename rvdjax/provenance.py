"""Provenance of stored results: which code, on which machine, flew which definition.

Every directory that stores results (study tables, verification evaluations, tuning outputs,
benchmark JSON: :func:`benchmark_block`) records two things:

* the **environment** (:func:`environment`): the rvdjax version, a SHA-256 of the package's
  source files, the git commit and whether the package's files differ from it (``dirty``),
  the jax, jaxlib, NumPy and Python versions and the device;
* the **definition** (:func:`canonical`, :func:`describe`): everything that defines a run
  (scenario values and the parameter arrays built from them, loop configuration, solver
  settings, requirement, dispersion, ...) as canonical JSON, and its SHA-256.

A resume, or a reuse of stored evaluations, goes through :func:`stamp`:

* a different definition stops with one line naming the first entries that differ;
* a different code version (source hash, jax or jaxlib) stops unless ``allow_code_change``;
  allowed, the new environment is recorded beside the first and the rows it writes are marked
  (:func:`row_marks`: ``provenance`` names the environment, ``code_changed`` is True);
* the device is recorded (per environment) but does not refuse: the engine gives the same
  results on every device to rounding, and a study may move between them.

The code version is the source hash, not the git commit: a commit that changes only docs
keeps it, an uncommitted edit of a module changes it. The commit and the dirty flag are there
for the reader, to find the code again.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import hashlib
import json
import math
import platform
import subprocess
from pathlib import Path

import numpy as np

__all__ = [
    "ProvenanceError",
    "environment",
    "code_identity",
    "canonical",
    "describe",
    "scenario_values",
    "digest",
    "differences",
    "stamp",
    "benchmark_block",
    "row_marks",
    "format_provenance",
    "summary",
    "summary_lines",
    "SMALL_ARRAY",
]

# arrays of at most this many entries are stored by value, longer ones by shape and hash
SMALL_ARRAY = 16
DIGITS = 12  # significant digits of the floats in a definition
CODE_KEYS = ("rvdjax", "source_sha256", "jax", "jaxlib")
PACKAGE = Path(__file__).resolve().parent


class ProvenanceError(ValueError):
    """A stored result does not match what would be computed now (one line, names why)."""


# ----------------------------------------------------------------------------- environment


def _git(*args) -> str | None:
    try:
        r = subprocess.run(
            ["git", "-C", str(PACKAGE.parent), *args],
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return r.stdout.strip() if r.returncode == 0 else None


def source_sha256(package: Path = PACKAGE) -> str:
    """SHA-256 over the package's ``*.py`` files (relative path and content, sorted)."""
    h = hashlib.sha256()
    for p in sorted(package.rglob("*.py")):
        if "__pycache__" in p.parts:
            continue
        h.update(p.relative_to(package).as_posix().encode())
        h.update(b"\0")
        h.update(p.read_bytes())
        h.update(b"\0")
    return h.hexdigest()


@functools.lru_cache(maxsize=1)
def _static_environment() -> dict:
    import importlib.metadata as md

    import jax
    import jaxlib

    try:
        version = md.version("rvdjax")
    except md.PackageNotFoundError:
        version = "unknown"
    commit = _git("rev-parse", "HEAD")
    dirty = None
    if commit is not None:
        status = _git("status", "--porcelain", "--untracked-files=all", "--", "rvdjax")
        dirty = None if status is None else bool(status)
    return {
        "rvdjax": version,
        "source_sha256": source_sha256(),
        "git_commit": commit,
        "git_dirty": dirty,
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "machine": f"{platform.system()} {platform.machine()}",
    }


def _devices() -> tuple[str, int]:
    import jax

    devs = jax.devices()
    return ", ".join(sorted({f"{d.platform}:{d.device_kind}" for d in devs})), len(devs)


def environment(device: str | None = None) -> dict:
    """The running code and machine (module docstring). ``device``: what the results were
    computed on, when not JAX's default devices (e.g. ``--device cpu`` on a GPU machine).
    ``device`` names the kind (platform:kind), ``device_count`` how many JAX sees (not part
    of an environment's identity: a study sharded over devices flies the same bits). The git
    fields are None outside a git checkout."""
    kind, count = _devices()
    return {**_static_environment(), "device": device or kind, "device_count": count}


def code_identity(env: dict) -> dict:
    """The entries of an environment that make a different code version."""
    return {k: env.get(k) for k in CODE_KEYS}


def _env_id(env: dict) -> str:
    keys = (*CODE_KEYS, "device")
    return digest({k: env.get(k) for k in keys})[:12]


# ----------------------------------------------------------------------------- definition


def canonical(obj, small: int = SMALL_ARRAY):
    """``obj`` as plain JSON data, the same for equal values: dataclasses, NamedTuples and
    dicts become dicts (sorted keys), sequences lists, arrays their values (at most ``small``
    entries) or ``{"shape", "dtype", "sha256"}`` (the hash of their values to :data:`DIGITS`
    digits relative to the largest), floats
    to :data:`DIGITS` significant digits (non-finite ones as strings), enums by name,
    functions by qualified name; anything else by its ``repr``."""
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, enum.Enum):
        return f"{type(obj).__name__}.{obj.name}"
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        # 12 significant digits: the same value computed by another libm or BLAS (one ulp
        # apart) must not read as another definition
        return float(f"{v:.{DIGITS}g}") if math.isfinite(v) else repr(v)
    if isinstance(obj, Path):
        return str(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        # a renamed field keeps the name stored definitions know it by ("stored_as"); a field
        # added later is left out at the value that flies the runs as before it existed
        # ("stored_unless"), so definitions stored before it still match
        out = {}
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name)
            if callable(v) and not dataclasses.is_dataclass(v):
                continue
            if "stored_unless" in f.metadata and v == f.metadata["stored_unless"]:
                continue
            out[f.metadata.get("stored_as", f.name)] = canonical(v, small)
        return out
    if isinstance(obj, tuple) and hasattr(obj, "_fields"):  # NamedTuple
        out = {}
        for k, v in zip(obj._fields, obj, strict=True):
            if getattr(type(v), "STORED_FLAT", False):  # a record stored as its parent's fields
                out.update(canonical(v, small))
            else:
                out[k] = canonical(v, small)
        return out
    if isinstance(obj, dict):
        return {str(k): canonical(obj[k], small) for k in sorted(obj, key=str)}
    if isinstance(obj, (list, tuple)):
        return [canonical(v, small) for v in obj]
    if hasattr(obj, "shape") and hasattr(obj, "dtype"):  # numpy / jax arrays
        a = np.asarray(obj)
        if a.dtype == object:
            return [canonical(v, small) for v in a.tolist()]
        if a.dtype.kind == "b":
            a = a.astype(np.int64)
        if a.ndim == 0:
            return canonical(a.item(), small)
        if a.size <= small:
            return canonical(a.tolist(), small)
        if a.dtype.kind in "fc":
            # DIGITS digits relative to the largest entry (an entry that is 0 on one machine
            # and 1e-17 on another is the same value)
            w = a.astype(np.float64).ravel()
            scale = float(np.max(np.abs(w[np.isfinite(w)]), initial=0.0)) or 1.0
            q = np.where(np.isfinite(w), np.round(w / scale, DIGITS) + 0.0, w)
            text = f"{scale:.{DIGITS}g}:" + ",".join(repr(float(v)) for v in q)
        else:
            text = ",".join(str(int(v)) for v in a.ravel())
        return {
            "shape": list(a.shape),
            "dtype": str(a.dtype),
            "sha256": hashlib.sha256(text.encode()).hexdigest(),
        }
    if callable(obj):
        return f"{getattr(obj, '__module__', '?')}.{getattr(obj, '__qualname__', repr(obj))}"
    return repr(obj)


# a scenario's fields that do not change a run (words for the reader; the name is the
# caller's, e.g. a study's spec, and a scenario file's copy has its own path)
SCENARIO_WORDS = ("name", "description", "published", "assumptions", "source")


def scenario_values(scenario) -> dict:
    """A scenario record's values that define its runs (its words left out)."""
    c = canonical(scenario)
    return {k: v for k, v in c.items() if k not in SCENARIO_WORDS}


def describe(**parts) -> dict:
    """A run definition from named parts (each made :func:`canonical`)."""
    return {k: canonical(v) for k, v in parts.items()}


def digest(obj) -> str:
    """SHA-256 of canonical JSON."""
    text = json.dumps(canonical(obj), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def differences(stored, current, path: str = "", limit: int = 3) -> list[str]:
    """The first ``limit`` entries where two canonical values differ, as ``path: stored ->
    current`` (long values shortened)."""
    out: list[str] = []

    def short(v) -> str:
        s = json.dumps(v, sort_keys=True)
        if isinstance(v, dict) and "sha256" in v:
            s = f"array {tuple(v['shape'])} #{v['sha256'][:8]}"
        return s if len(s) <= 40 else s[:37] + "..."

    def walk(a, b, p):
        if len(out) >= limit or a == b:
            return
        if isinstance(a, dict) and isinstance(b, dict) and not ("sha256" in a and "sha256" in b):
            for k in sorted(set(a) | set(b)):
                if k not in a:
                    out.append(f"{p}{k}: (absent) -> {short(b[k])}")
                elif k not in b:
                    out.append(f"{p}{k}: {short(a[k])} -> (absent)")
                else:
                    walk(a[k], b[k], f"{p}{k}.")
                if len(out) >= limit:
                    return
        elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
            for i, (x, y) in enumerate(zip(a, b, strict=True)):
                walk(x, y, f"{p.rstrip('.')}[{i}].")
        else:
            out.append(f"{p.rstrip('.')}: {short(a)} -> {short(b)}")

    walk(canonical(stored), canonical(current), path)
    return out


# ----------------------------------------------------------------------------- checking


def stamp(
    stored: dict | None,
    definition: dict,
    *,
    allow_code_change: bool = False,
    where: str = "",
    device: str | None = None,
) -> dict:
    """The provenance block to store with results defined by ``definition``.

    ``stored``: the block already on disk (None: a new directory). A different definition
    raises :class:`ProvenanceError` naming what differs; a different code version raises
    unless ``allow_code_change`` (then the new environment is added and becomes
    ``current``). ``where`` starts the message (e.g. ``"--out DIR"``).

    The block: ``definition`` (canonical), ``definition_sha256``, ``environments`` (id ->
    :func:`environment`), ``first`` and ``current`` (ids)."""
    definition = canonical(definition)
    h = digest(definition)
    env = environment(device)
    eid = _env_id(env)
    prefix = f"{where}: " if where else ""
    if stored is None:
        return {
            "definition": definition,
            "definition_sha256": h,
            "environments": {eid: env},
            "first": eid,
            "current": eid,
        }
    if "definition_sha256" not in stored:
        if not allow_code_change:
            raise ProvenanceError(
                f"{prefix}its results carry no provenance (written by an older rvdjax); "
                "pass --allow-code-change to continue, marking the new rows"
            )
        stored = {
            "definition": definition,
            "definition_sha256": h,
            "environments": {"unrecorded": {"rvdjax": "unrecorded"}},
            "first": "unrecorded",
            "current": "unrecorded",
        }
    if stored["definition_sha256"] != h:
        diff = "; ".join(differences(stored.get("definition"), definition))
        raise ProvenanceError(
            f"{prefix}the stored runs were defined differently ({diff or 'definition hash'}); "
            "choose another directory"
        )
    first = stored["environments"][stored["first"]]
    if code_identity(first) != code_identity(env) and not allow_code_change:
        diff = "; ".join(differences(code_identity(first), code_identity(env)))
        raise ProvenanceError(
            f"{prefix}stored by another code version ({diff}); pass --allow-code-change to "
            "continue, marking the new rows"
        )
    envs = dict(stored["environments"])
    envs.setdefault(eid, env)
    return {**stored, "environments": envs, "current": eid}


def benchmark_block(benchmark: str, options: dict, device: str | None = None) -> dict:
    """The provenance block of a benchmark's output (a :func:`stamp` of a new directory):
    the definition is the benchmark's name (its script or command) and its options (values
    that are not plain data, such as argparse's handlers, left out)."""
    plain = (str, int, float, bool, type(None), list, tuple)
    kept = {k: v for k, v in options.items() if isinstance(v, plain)}
    return stamp(None, describe(benchmark=benchmark, options=kept), device=device)


def row_marks(block: dict) -> dict:
    """The columns every row written under ``block`` carries: ``provenance`` (the id of the
    environment in the block's ``environments``) and ``code_changed`` (its code version
    differs from the directory's first)."""
    envs = block["environments"]
    cur, first = envs[block["current"]], envs[block["first"]]
    return {
        "provenance": block["current"],
        "code_changed": code_identity(cur) != code_identity(first),
    }


def format_provenance(block: dict, rows: dict | None = None) -> list[str]:
    """Printable lines: each environment (with its rows when ``rows`` {id: count} is given)
    and the definition hash."""
    out = [f"definition sha256 {block['definition_sha256'][:16]}"]
    for eid, env in block["environments"].items():
        if env.get("rvdjax") == "unrecorded":
            line = "rows without provenance (older rvdjax)"
        else:
            commit = env.get("git_commit")
            git = (
                "no git checkout"
                if commit is None
                else f"git {commit[:10]}{' (dirty)' if env.get('git_dirty') else ''}"
            )
            line = (
                f"rvdjax {env['rvdjax']} (source {env['source_sha256'][:10]}, {git}), "
                f"jax {env['jax']} / jaxlib {env['jaxlib']}, {env['device']}"
                f" ({env.get('device_count', '?')} devices)"
            )
        tag = " [first]" if eid == block["first"] else " [code changed]"
        if eid != block["first"] and code_identity(env) == code_identity(
            block["environments"][block["first"]]
        ):
            tag = ""
        n = "" if rows is None else f": {rows.get(eid, 0)} rows"
        out.append(f"{eid}{tag} {line}{n}")
    return out


def summary(block: dict | None, table=None) -> dict | None:
    """A stored block with the rows of ``table`` (a DataFrame with the ``provenance`` and
    ``code_changed`` columns) counted by environment; rows written before provenance was
    recorded count as ``unrecorded``. None when nothing was recorded."""
    if block is None:
        block = {}
    out = dict(block)
    if table is not None:
        if "provenance" in table:
            ids = table["provenance"].fillna("unrecorded").astype(str)
        else:
            ids = np.full(len(table), "unrecorded")
        out["rows_used"] = {
            str(k): int(v) for k, v in zip(*np.unique(ids, return_counts=True), strict=True)
        }
        changed = table["code_changed"].fillna(True) if "code_changed" in table else ids != ""
        out["rows_code_changed"] = int(np.sum(np.asarray(changed, bool)))
    return out or None


def summary_lines(block: dict | None) -> list[str]:
    """Printable lines of :func:`summary`'s result (or of a stored block)."""
    if not block or "definition_sha256" not in block:
        n = (block or {}).get("rows_used", {}).get("unrecorded")
        return [f"none recorded{'' if n is None else f' ({n} rows)'}: written by an older rvdjax"]
    out = format_provenance(block, block.get("rows_used"))
    if block.get("rows_code_changed"):
        out.append(
            f"{block['rows_code_changed']} rows were flown by another code version than the "
            "first (--allow-code-change; column code_changed)"
        )
    return out
