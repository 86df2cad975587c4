"""The one table-and-JSON writer of the measurements: a Markdown table printed (and optionally saved beside the
JSON), the numbers written as JSON, and one line saying where."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

Column = Tuple[str, Callable[[Dict[str, Any]], Any]]


def markdown_table(rows: Sequence[Dict[str, Any]], columns: Sequence[Column]) -> str:
    """One Markdown table: a header of the columns' names, one line per row of the columns' cells."""
    lines = ["| " + " | ".join(name for name, _ in columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(str(cell(row)) for _, cell in columns) + " |" for row in rows]
    return "\n".join(lines)


def write_report(tool: str, table: str, payload: Any, json_path: Path, markdown_path: Optional[Path] = None) -> List[Path]:
    """Print ``table``, write ``payload`` as JSON to ``json_path`` (and the table to ``markdown_path``), and say
    where in one line. Returns the files written."""
    print()
    print(table)
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(payload, indent=2, default=str))
    written = [json_path]
    if markdown_path is not None:
        markdown_path.parent.mkdir(parents=True, exist_ok=True)
        markdown_path.write_text(table + "\n")
        written.append(markdown_path)
    print(f"\n{tool}: wrote {' and '.join(map(str, written))}")
    return written
