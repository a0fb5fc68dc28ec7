"""The documentation checker (.ci/check_docs.py) on tiny pages: each defect it looks for is
found, and a page without it passes. No mkdocs build here."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

_PATH = Path(__file__).resolve().parent.parent / ".ci" / "check_docs.py"
_spec = importlib.util.spec_from_file_location("check_docs", _PATH)
check_docs = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(check_docs)

IMG = '<img alt="" src="data:image/png;base64,iVBORw0KGgo=">'


@pytest.mark.parametrize(
    "rel, html, found",
    [
        ("guide", "<p>Steps:\n- one\n- two</p>", "list collapsed"),
        ("api/x", "<p>See :class:<code>rvdjax.ocp.OCP</code>.</p>", "leftover role"),
        ("api/x", "<p>Call :func:`fly` once.</p>", "leftover role"),
        ("notebooks/x", f"<p>$$L = w_e E$$</p>{IMG}", "unrendered math"),
        (
            "notebooks/x",
            "<h2>Plots</h2><pre><code>print(1)</code></pre>",
            "without an output image",
        ),
    ],
)
def test_page_defect_found(rel, html, found):
    problems = check_docs.page_defects(rel, html)
    assert len(problems) == 1 and found in problems[0], problems


@pytest.mark.parametrize(
    "rel, html",
    [
        ("guide", "<p>Steps:</p>\n<ul>\n<li>one\n<ul>\n<li>two</li>\n</ul></li>\n</ul>"),
        ("guide", "<p>A range\n-5 to 5 and x - y.</p><pre><code>- not a list\n$$</code></pre>"),
        ("api/x", '<p>See <a href="../ocp/#rvdjax.ocp.OCP"><code>OCP</code></a>.</p>'),
        ("notebooks/x", f'<div class="arithmatex">\\[L = w_e E\\]</div>{IMG}'),
    ],
)
def test_clean_page_passes(rel, html):
    assert check_docs.page_defects(rel, html) == []


def test_source_nested_list_indent():
    bad = "- parent\n  - child at two spaces\n"
    good = "- parent\n    - child at four\n\n1. first\n    - nested under a number\n"
    assert [n for n, _ in check_docs.source_defects(bad)] == [2]
    assert check_docs.source_defects(good) == []


def test_source_continuation_block_indent():
    bad = "- item:\n\n  | a | b |\n  | - | - |\n\n    more text\n"
    good = "- item, a lazy\n  continuation line\n\n    a second paragraph\n\nAfter the list.\n"
    fenced = "- item\n\n```text\n  - not markdown\n```\n"
    assert [n for n, _ in check_docs.source_defects(bad)] == [3]
    assert check_docs.source_defects(good) == []
    assert check_docs.source_defects(fenced) == []


def test_main_on_a_site(tmp_path):
    (tmp_path / "index.html").write_text("<p>Home</p>")
    (tmp_path / "guide").mkdir()
    (tmp_path / "guide" / "index.html").write_text("<p>Steps:\n- one</p>")
    assert check_docs.main([str(tmp_path)]) == 1
    (tmp_path / "guide" / "index.html").write_text("<ul><li>one</li></ul>")
    assert check_docs.main([str(tmp_path)]) == 0
