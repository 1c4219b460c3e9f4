"""Sphinx configuration of the rkident documentation (build: see README, "Install")."""

import os
import re
import sys

sys.path.insert(0, os.path.abspath(".."))

project = "rkident"
author = "rkident developers"
copyright = "rkident developers"  # noqa: A001 (the name Sphinx reads)

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "myst_parser",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "_generated"]

# Google-style docstrings; the documented order of members is the source order.
napoleon_google_docstring = True
napoleon_numpy_docstring = False
# Attributes sections as :ivar: fields, so a documented property is described once.
napoleon_use_ivar = True
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"members": True, "show-inheritance": True}
# Headings of the Markdown pages (benchmarks) get anchors for in-page links.
myst_heading_anchors = 3

html_theme = "alabaster"
html_title = "rkident"


# The docstrings write array shapes as plain text, ``(*batch, n)`` and ``**options``, which
# reStructuredText would read as the start of emphasis. Escape such a star (outside ``literal``
# spans and literal blocks) so that shapes render as written; real ``*emphasis*`` is untouched.
_SHAPE_STAR = re.compile(
    r"(?:(?<=[(\[,])|(?<=, ))\*(?=[A-Za-z_])(?!\w+\*)"  # (*batch, n), (n, *batch)
    r"|(?<![\w*\\])\*\*(?=[A-Za-z_])(?!\w+\*\*)"  # **options
)
_LITERAL = re.compile(r"``.*?``")


def _escape_shape_stars(line: str) -> str:
    parts, last = [], 0
    for m in _LITERAL.finditer(line):
        parts += [_SHAPE_STAR.sub(lambda s: "\\" + "\\".join(s.group()), line[last : m.start()])]
        parts += [m.group()]
        last = m.end()
    parts += [_SHAPE_STAR.sub(lambda s: "\\" + "\\".join(s.group()), line[last:])]
    return "".join(parts)


def _process_docstring(app, what, name, obj, options, lines):
    literal_indent = None  # indentation of the paragraph that opened a literal block
    for i, line in enumerate(lines):
        indent = len(line) - len(line.lstrip())
        if literal_indent is not None:
            if not line.strip() or indent > literal_indent:
                continue
            literal_indent = None
        if line.rstrip().endswith("::"):
            literal_indent = indent
        if not line.lstrip().startswith(">>>"):
            lines[i] = _escape_shape_stars(line)


# "eq. 2.17-2.20, 2.24", "eq. (2.150)-(2.158)", "eq. 4.92/4.93": a run of equation numbers.
_EQ_REF = re.compile(
    r"\b(?:eqs?\.|equations?)\s*\(?"
    r"((?:\d+\.\d+[a-z]?\)?(?:[-–/,]\s*|\s+and\s+|,?\s*\(?(?=\d+\.\d))*)+)"
)
_EQ_NUMBER = re.compile(r"\d+\.\d+[a-z]?")


def _equation_table(root: str) -> str:
    """An RST table: each module of integrators/ and sysid/ and the notes' equations it cites."""
    rows = []
    for package in ("integrators", "sysid", "sysid/zoo"):
        for path in sorted(os.listdir(os.path.join(root, package))):
            if not path.endswith(".py") or path == "__init__.py":
                continue
            text = open(os.path.join(root, package, path), encoding="utf-8").read()
            found = {n for m in _EQ_REF.finditer(text) for n in _EQ_NUMBER.findall(m.group(1))}
            if found:
                key = lambda n: tuple(int(x) for x in re.findall(r"\d+", n)) + (n[-1],)  # noqa: E731
                module = package.replace("/", ".") + "." + path[:-3]
                rows.append(f"   * - ``{module}``\n     - {', '.join(sorted(found, key=key))}")
    header = ".. list-table::\n   :header-rows: 1\n   :widths: 30 70\n\n"
    header += "   * - module\n     - equations\n"
    return header + "\n".join(rows) + "\n"


def _write_generated(app):
    out = os.path.join(app.srcdir, "_generated")
    os.makedirs(out, exist_ok=True)
    table = _equation_table(os.path.dirname(os.path.abspath(app.srcdir)))
    path = os.path.join(out, "equations.rst")
    if not os.path.exists(path) or open(path, encoding="utf-8").read() != table:
        with open(path, "w", encoding="utf-8") as fh:
            fh.write(table)


def setup(app):
    app.connect("builder-inited", _write_generated)
    app.connect("autodoc-process-docstring", _process_docstring)
