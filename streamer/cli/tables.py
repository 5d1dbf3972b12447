"""Tables and numbers for the terminal (not a subcommand): fit the width, never cut a value.

A value cut in half is worse than no value, so `fit_table` lays tables out itself instead of Rich's
ellipsis: value columns get their longest value and never break, text columns wrap at spaces, headers
wrap (units go in them), optional columns show while they fit (a caption names the rest), and a table
that cannot fit becomes records. A `cut` column (a listing's error) is the exception: one line, ending
in "…", its caption saying where the whole text is. `number` prints without an exponent.
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from rich.cells import cell_len
from rich.table import Table
from rich.text import Text

# A column costs its content width plus 2 spaces of padding and 1 border; the table 1 more border.
_PER_COLUMN = 3
_MIN_TEXT = 16  # a wrapping text column is never narrower than this (or its longest word)
_MIN_CUT = 12  # a cut column is given this much before optional columns are added


@dataclass(frozen=True)
class Col:
    """One column: `header` (units in brackets), `justify`, `text` (wraps at spaces, takes the rest of the
    width) and `drop` (0: always shown; columns with a higher value are dropped first when narrow)."""

    header: str
    justify: str = "left"
    text: bool = False
    drop: int = 0
    cut: bool = False  # one line, cut to the width left ("…"); `whole` says where the whole text is
    whole: str = ""


def number(value: Any, digits: int = 4, *, none: str = "-") -> str:
    """`value` with about `digits` significant digits and no exponent: 1000, 12.35, 0.001235, -3."""
    if value is None or isinstance(value, bool):
        return none
    try:
        x = float(value)
    except (TypeError, ValueError):
        return str(value)
    if not math.isfinite(x):
        return str(x)
    if x == 0.0:
        return "0"
    if isinstance(value, int):
        return str(value)
    magnitude = math.floor(math.log10(abs(x)))
    decimals = min(9, max(0, digits - 1 - magnitude))
    text = f"{x:.{decimals}f}"
    return "0" if float(text) == 0.0 else text


def _words_width(text: str) -> int:
    return max((cell_len(w) for w in text.split()), default=0)


def _wrap_header(header: str, width: int) -> str:
    lines: list[str] = []
    for part in header.split("\n"):
        lines.extend(textwrap.wrap(part, width=max(1, width), break_long_words=False) or [""])
    return "\n".join(lines)


def fit_table(
    columns: Sequence[Col],
    rows: Sequence[Sequence[str]],
    width: int,
    *,
    title: str | None = None,
    more: str = "--json",
) -> Table:
    """A rich Table of `rows` that fits `width` columns of terminal (see the module docstring)."""
    cols = list(range(len(columns)))
    rows = [[" ".join(str(v).split()) if columns[i].cut else str(v) for i, v in enumerate(r)] for r in rows]

    def content(i: int) -> int:
        return max((cell_len(line) for r in rows for line in r[i].split("\n")), default=0)

    def need(i: int) -> int:  # the width a column needs to show every value unbroken
        c = columns[i]
        header_min = _words_width(c.header)
        if c.cut:
            return max(header_min, min(_MIN_CUT, content(i)), 1)
        if c.text:
            longest_word = max((_words_width(r[i]) for r in rows), default=0)
            return max(header_min, min(_MIN_TEXT, max(content(i), 1)), longest_word if longest_word <= 40 else 0)
        return max(header_min, content(i), 1)

    def total(indices: list[int]) -> int:
        return sum(need(i) for i in indices) + _PER_COLUMN * len(indices) + 1

    # the required columns, then each optional one that still fits, the least droppable first
    cols = [i for i in cols if columns[i].drop == 0]
    dropped: list[int] = []
    for i in sorted((i for i in range(len(columns)) if columns[i].drop > 0), key=lambda i: (columns[i].drop, i)):
        if total(sorted([*cols, i])) <= width:
            cols = sorted([*cols, i])
        else:
            dropped.append(i)
    floor = {i: max(1, _words_width(columns[i].header)) for i in cols if columns[i].cut}
    if total(cols) - sum(need(i) - floor[i] for i in floor) > width:
        return _records(columns, rows, title)
    fits = True
    spare = width - total(cols)
    widths = {i: need(i) for i in cols}
    for i in floor:  # short of width: the cut columns give up what they must, down to their header's width
        give = min(max(0, -spare), widths[i] - floor[i])
        widths[i] -= give
        spare += give
    text_cols = [i for i in cols if columns[i].text or columns[i].cut]
    for i in text_cols:
        # the text columns share what is left, the first gets the remainder
        share = spare // len(text_cols) + (spare % len(text_cols) if i == text_cols[0] else 0)
        widths[i] = min(widths[i] + share, max(widths[i], content(i)))
    notes: list[str] = []
    if dropped:
        names = ", ".join(columns[i].header.replace("\n", " ") for i in sorted(dropped))
        notes.append(f"not shown at {width} columns: {names} (wider terminal, or {more})")
    for i in cols:
        c = columns[i]
        if c.cut and any(cell_len(r[i]) > widths[i] for r in rows):
            notes.append(f"{c.header.replace(chr(10), ' ')} cut to the line" + (f": {c.whole}" if c.whole else ""))
    caption = "; ".join(notes) if notes else None
    table = Table(title=Text(title) if title else None, caption=Text(caption) if caption else None,
                  caption_justify="left", title_justify="left")
    for i in cols:
        c = columns[i]
        w = widths[i]
        header = Text(_wrap_header(c.header, w))  # Text: "[s]" is a unit here, not rich markup
        if c.cut:
            table.add_column(header, justify=c.justify, no_wrap=True, overflow="ellipsis",  # type: ignore[arg-type]
                             min_width=w, max_width=w)
        elif fits and not c.text:
            table.add_column(header, justify=c.justify, no_wrap=True, min_width=w, max_width=w)  # type: ignore[arg-type]
        else:  # text wraps at spaces (a word longer than the column folds: shown whole, never cut)
            table.add_column(header, justify=c.justify, overflow="fold", min_width=w)  # type: ignore[arg-type]
    for r in rows:
        table.add_row(*(Text(r[i]) for i in cols))
    return table


def _records(columns: Sequence[Col], rows: Sequence[Sequence[str]], title: str | None) -> Table:
    """The narrow layout: one "field  value" line per column and row, values folded, nothing dropped."""
    table = Table(title=Text(title) if title else None, title_justify="left", show_header=False)
    table.add_column("field", no_wrap=True)
    table.add_column("value", overflow="fold")
    for r in rows:
        for k, (c, v) in enumerate(zip(columns, r, strict=True)):
            table.add_row(Text(c.header.replace("\n", " ")), Text(v or "-"), end_section=k == len(columns) - 1)
    return table
