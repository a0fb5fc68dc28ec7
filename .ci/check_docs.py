"""Check the built documentation site for pages that do not render as written.

    python .ci/check_docs.py site

Defects looked for in the HTML that ``mkdocs build`` wrote (each reported with its page):

* a paragraph holding a line that starts with "- " (a list that collapsed into text: a
  nested list indented less than Python-Markdown's four spaces, or a bullet after a
  paragraph without a blank line);
* a notebook page without an output image (a notebook rendered without its outputs);
* a leftover Sphinx role (``:class:``, ``:func:``, ...) or a ``$$`` outside code (a docstring
  role that leaked, math that was not rendered).

With ``--sources DIR`` the Markdown sources are read as well: a list item indented by one to
three spaces under another item (Python-Markdown nests only at four: the sub-bullets become
items of the parent list) is a defect, and so is a continuation block (a paragraph, a table
after a blank line) of a list item indented by one to three spaces.

Exit status 1 with one line per defect, 0 when there is none. Standard library only.
"""

from __future__ import annotations

import re
import sys
from html.parser import HTMLParser
from pathlib import Path

ROLE = re.compile(r":(?:class|func|meth|mod|attr|data|exc|obj|ref):`?")
SKIP_TAGS = {"pre", "code", "script", "style"}


class _Page(HTMLParser):
    """Paragraph texts, text outside code, and whether an output image is present."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.paragraphs: list[str] = []
        self.text: list[str] = []
        self.images = 0
        self._skip = 0
        self._para: list[str] | None = None

    def handle_starttag(self, tag, attrs):
        if tag in SKIP_TAGS:
            self._skip += 1
        elif tag == "p" and self._skip == 0:
            self._para = []
        elif tag == "img":
            src = dict(attrs).get("src") or ""
            if src.startswith("data:image/") or src.endswith((".png", ".svg", ".jpg")):
                self.images += 1

    def handle_endtag(self, tag):
        if tag in SKIP_TAGS:
            self._skip = max(0, self._skip - 1)
        elif tag == "p" and self._para is not None:
            self.paragraphs.append("".join(self._para))
            self._para = None

    def handle_data(self, data):
        if self._skip:
            return
        self.text.append(data)
        if self._para is not None:
            self._para.append(data)


def check(site: Path) -> list[str]:
    problems = []
    for page in sorted(site.rglob("index.html")):
        rel = page.parent.relative_to(site).as_posix() or "."
        if rel.startswith(("search", "assets")) or rel == "404":
            continue
        problems += page_defects(rel, page.read_text(encoding="utf-8"))
    return problems


def page_defects(rel: str, html: str) -> list[str]:
    """The defects of one built page; ``rel`` is its path in the site (``notebooks/NAME``)."""
    problems = []
    parser = _Page()
    parser.feed(html)
    parser.close()
    for para in parser.paragraphs:
        if any(line.lstrip().startswith("- ") for line in para.splitlines()[1:]):
            first = next(ln for ln in para.splitlines() if ln.strip())
            problems.append(f"{rel}: a list collapsed into a paragraph: {first[:70]!r}")
    text = "".join(parser.text)
    for m in ROLE.finditer(text):
        problems.append(
            f"{rel}: leftover role {m.group(0)!r}: {text[m.start() : m.start() + 60]!r}"
        )
    if "$$" in text:
        i = text.index("$$")
        problems.append(f"{rel}: unrendered math: {text[i : i + 60]!r}")
    if rel.startswith("notebooks/") and parser.images == 0:
        problems.append(f"{rel}: a notebook page without an output image")
    return problems


_ITEM = re.compile(r"^( *)(?:[-*+]|\d+\.) \S")


def check_sources(root: Path) -> list[str]:
    """Markdown sources (outside fenced code) whose lists Python-Markdown would not nest."""
    problems = []
    for path in sorted(root.rglob("*.md")):
        where = path.as_posix()
        problems += [f"{where}:{n}: {msg}" for n, msg in source_defects(path.read_text("utf-8"))]
    return problems


def source_defects(text: str) -> list[tuple[int, str]]:
    """(line, message) for each list defect of one Markdown text.

    * a list item under another item indented by a number of spaces that is not a multiple of
      four (Python-Markdown nests only at four: a sub-bullet at two becomes an item of the
      parent list);
    * a block after a blank line inside a list (a continuation paragraph, a table) indented by
      one to three spaces: it ends the list, and what follows at four spaces becomes code.
    """
    problems = []
    fenced = False
    in_list = False
    after_blank = False
    for n, line in enumerate(text.splitlines(), 1):
        if line.lstrip().startswith(("```", "~~~")):
            fenced = not fenced
            after_blank = False
            continue
        if fenced:
            continue
        if not line.strip():
            after_blank = True
            continue
        indent = len(line) - len(line.lstrip(" "))
        m = _ITEM.match(line)
        if m:
            if in_list and indent % 4:
                problems.append((n, f"a nested list item indented {indent} spaces (4 per level)"))
            in_list = True
        elif indent == 0:
            in_list = False
        elif in_list and after_blank and indent % 4:
            problems.append(
                (n, f"a list's continuation block indented {indent} spaces (4 per level)")
            )
        after_blank = False
    return problems


def main(argv=None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    sources = None
    if "--sources" in args:
        i = args.index("--sources")
        sources = Path(args[i + 1])
        del args[i : i + 2]
    site = Path(args[0] if args else "site")
    if not (site / "index.html").exists():
        print(f"check_docs: {site} holds no built site (mkdocs build first)", file=sys.stderr)
        return 2
    problems = check(site) + (check_sources(sources) if sources else [])
    for p in problems:
        print(p)
    print(f"check_docs: {len(problems)} defect(s) in {site}", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
