"""Output paths proven writable before any work: a file is created and removed where the
output will go (``os.access`` is not enough: root passes it on read-only and virtual file
systems such as /proc). Each check raises ValueError naming the option, the path and why."""

from __future__ import annotations

import os
import tempfile

__all__ = ["check_file", "check_dir"]


def _probe(directory: str, option: str, path: str) -> None:
    """Create and remove a temporary file in ``directory``."""
    try:
        fd, name = tempfile.mkstemp(prefix=".rvdjax-probe-", dir=directory)
    except OSError as err:
        raise ValueError(
            f"{option} {path!r}: cannot write in {directory!r} ({err.strerror or err})"
        ) from None
    os.close(fd)
    os.remove(name)


def check_file(path: str | None, option: str, formats: tuple[str, ...] | None = None) -> None:
    """ValueError unless the file ``path`` can be written: its extension is one of
    ``formats``, its directory exists and takes a new file, and an existing file is writable."""
    if path is None:
        return
    if formats is not None and os.path.splitext(path)[1].lower() not in formats:
        raise ValueError(
            f"{option} {path!r}: the file name must end in one of {', '.join(formats)}"
        )
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise ValueError(f"{option} {path!r}: directory {directory!r} does not exist")
    if os.path.isdir(path):
        raise ValueError(f"{option} {path!r} is a directory, not a file")
    if os.path.exists(path) and not os.access(path, os.W_OK):
        raise ValueError(f"{option} {path!r}: the file is not writable")
    _probe(directory, option, path)
    if os.path.exists(path):  # writable in place (a read-only mount refuses the open)
        try:
            with open(path, "ab"):
                pass
        except OSError as err:
            raise ValueError(
                f"{option} {path!r}: the file is not writable ({err.strerror})"
            ) from None


def check_dir(path: str | None, option: str) -> None:
    """ValueError unless the directory ``path`` can hold new files: an existing directory
    takes a file; a new one's nearest existing parent does (the directory is created later)."""
    if path is None:
        return
    full = os.path.abspath(path)
    if os.path.exists(full):
        if not os.path.isdir(full):
            raise ValueError(f"{option} {path!r} is a file, not a directory")
        _probe(full, option, path)
        return
    parent = os.path.dirname(full)
    while not os.path.exists(parent):
        parent = os.path.dirname(parent)
    if not os.path.isdir(parent):
        raise ValueError(f"{option} {path!r}: {parent!r} is a file, not a directory")
    _probe(parent, option, path)
