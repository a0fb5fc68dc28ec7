"""MkDocs hooks for the documentation site (mkdocs.yml, ``hooks:``).

* The notebooks live in ``notebooks/`` (jupytext percent-format ``.py`` scripts), outside
  ``docs/``: they are added to the site as ``notebooks/NAME.py`` pages, which mkdocs-jupyter
  then renders without executing them.
* The docstrings use Sphinx roles (``:class:`~rvdjax.ocp.OCP```); mkdocstrings renders the
  code span but keeps the role's text. Each role becomes a cross-reference here: an optional
  mkdocs-autorefs reference, a link where the target is documented on the site (a dotted
  path such as ``rvdjax.ocp.OCP``), plain code otherwise (a name relative to its module).
  ``~`` shows the last component only, as in Sphinx. The second colon of a reST
  literal-block marker (``states::``) ending a paragraph is dropped.
* The notebooks' display math (``$$...$$`` in a Markdown cell, left as text by nbconvert) is
  marked up as pymdownx.arithmatex does it for the Markdown pages, so that the one MathJax
  of the site (``extra_javascript``) renders both; the notebook template's own MathJax
  loader (an empty ``src``) is dropped.
"""

from __future__ import annotations

import re
from pathlib import Path

from mkdocs.plugins import event_priority
from mkdocs.structure.files import File

_ROOT = Path(__file__).resolve().parent
_NOTEBOOKS = _ROOT / "notebooks"
_ROLE = re.compile(r":(?:mod|class|func|meth|data|attr|exc|obj):<code>(~?)([^<]+)</code>")
_LITERAL_MARKER = re.compile(r"::</p>")
_DISPLAY_MATH = re.compile(r"\$\$([^$<]+?)\$\$")
_NB_MATHJAX = re.compile(r"<!-- Load mathjax -->.*?<!-- End of mathjax configuration -->", re.S)


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


def _autoref(m: re.Match) -> str:
    tilde, target = m.groups()
    identifier = target.removesuffix("()")
    shown = target.rsplit(".", 1)[-1] if tilde else target
    return f'<autoref identifier="{identifier}" optional><code>{shown}</code></autoref>'


def _math(m: re.Match) -> str:
    return f'<div class="arithmatex">\\[{m.group(1).strip()}\\]</div>'


def on_page_content(html, page, config, files):
    src = page.file.src_uri
    if src.startswith("notebooks/"):
        html = _NB_MATHJAX.sub("", html)
        # a paragraph that is one display formula becomes the formula's block
        html = re.sub(r"<p>(\$\$[^$<]+?\$\$)</p>", r"\1", html)
        return _DISPLAY_MATH.sub(_math, html)
    if not src.startswith("api/"):
        return html
    return _LITERAL_MARKER.sub(":</p>", _ROLE.sub(_autoref, html))
