"""What a command or a benchmark prints to a terminal by default: aligned columns and wrapped prose,
every line within ``WIDTH`` characters (``hil run``'s and ``hil gap``'s summaries, the benches'; it
registers no command).

Why: a reader decides on a few columns; a table wider than the terminal wraps into noise.  Every
figure stays in ``--json`` and, where a bench has one, in its ``--markdown`` table.
"""
from __future__ import annotations

import textwrap

#: the longest line a summary prints by default
WIDTH = 100


def columns(head: list[str], rows: list[list[str]], indent: str = "") -> str:
    """``head`` and ``rows`` as aligned text: the first column left-aligned, the others right-aligned,
    two spaces between columns."""
    widths = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(head)]

    def line(cells):
        return indent + "  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(cells, widths)))

    return "\n".join([line(head)] + [line(r) for r in rows])


def wrap(text: str, indent: str = "", first: str | None = None) -> str:
    """``text`` filled to ``WIDTH``: continuation lines start with ``indent``, the first with ``first``
    (default ``indent``).  Words longer than a line (a path, a JSON value) are broken."""
    return textwrap.fill(text.strip(), WIDTH, initial_indent=indent if first is None else first,
                         subsequent_indent=indent, break_on_hyphens=False)


def wrap_lines(text: str) -> str:
    """Every line of ``text`` filled to ``WIDTH``, its continuation lines indented 4 more than it."""
    out = []
    for line in text.splitlines():
        lead = line[:len(line) - len(line.lstrip())]
        out.append(wrap(line, indent=lead + "    ", first=lead) if line.strip() else "")
    return "\n".join(out)
