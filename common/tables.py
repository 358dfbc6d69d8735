"""Tables as text: aligned columns for a terminal, or Markdown. The one table writer of every command."""

from __future__ import annotations

from collections.abc import Sequence


def _cells(head: Sequence[object], rows: Sequence[Sequence[object]]) -> list[list[str]]:
    out = [[str(c) for c in head], *([str(c) for c in r] for r in rows)]
    if any(len(r) != len(head) for r in out):
        raise ValueError(f"every row needs {len(head)} cells")
    return out


def text_table(
    head: Sequence[object], rows: Sequence[Sequence[object]], align: str = "", rule: bool = True
) -> str:
    """Columns padded to their widest cell, two spaces apart, with a dashed rule under the head.

    Args:
        head: Column titles.
        rows: Cells (anything; printed with str()).
        align: One character per column, `<` (left, the default for missing ones) or `>` (right).
        rule: Draw the dashed line under the head.
    """
    cells = _cells(head, rows)
    widths = [max(len(r[i]) for r in cells) for i in range(len(head))]
    sides = [align[i] if i < len(align) else "<" for i in range(len(head))]
    lines = [
        "  ".join(f"{c:{s}{w}}" for c, s, w in zip(r, sides, widths, strict=True)).rstrip() for r in cells
    ]
    if rule:
        lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def markdown_table(head: Sequence[object], rows: Sequence[Sequence[object]]) -> str:
    """A GitHub Markdown table."""
    cells = _cells(head, rows)
    lines = ["| " + " | ".join(r) + " |" for r in cells]
    lines.insert(1, "| " + " | ".join("---" for _ in head) + " |")
    return "\n".join(lines)
