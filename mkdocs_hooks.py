"""MkDocs hooks for the documentation site (mkdocs.yml, ``hooks:``).

* The notebooks live in ``notebooks/`` (jupytext percent-format ``.py`` scripts), outside
  ``docs/``: they are added to the site as ``notebooks/NAME.py`` pages, which mkdocs-jupyter
  then renders without executing them.
* The docstrings use Sphinx roles (``:class:`~rvdjax.ocp.OCP```); mkdocstrings renders the
  code span but keeps the role's text (and the ``~``), which are dropped here, as is the
  second colon of a reST literal-block marker (``states::``) ending a paragraph.
"""

from __future__ import annotations

import re
from pathlib import Path

from mkdocs.plugins import event_priority
from mkdocs.structure.files import File

_ROOT = Path(__file__).resolve().parent
_NOTEBOOKS = _ROOT / "notebooks"
_ROLE = re.compile(r":(?:mod|class|func|meth|data|attr|exc|obj):<code>~?")
_LITERAL_MARKER = re.compile(r"::</p>")


@event_priority(100)  # before mkdocs-jupyter's on_files, which turns .py files into pages
def on_files(files, config):
    for path in sorted(_NOTEBOOKS.glob("*.py")):
        # a plain File whose src_dir is the repository (not File.generated: mkdocs-jupyter's
        # NotebookFile wrapper recomputes abs_src_path from src_dir, None for generated files)
        files.append(
            File(
                f"notebooks/{path.name}",
                src_dir=str(_ROOT),
                dest_dir=config["site_dir"],
                use_directory_urls=config["use_directory_urls"],
            )
        )
    return files


def on_page_content(html, page, config, files):
    if not page.file.src_uri.startswith("api/"):
        return html
    return _LITERAL_MARKER.sub(":</p>", _ROLE.sub("<code>", html))
