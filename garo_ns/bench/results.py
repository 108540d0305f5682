"""Writing a benchmark result: the JSON, then its Markdown table and plot next to it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable, Dict, Tuple


def publish(result: Dict[str, Any], output: Path, report: Callable[[Dict[str, Any], Path], Tuple[Path, Path]]) -> None:
    """Write `result` to `output` (JSON), then `report(result, output)`'s table and plot; print the table."""
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(json.dumps(result, indent=2))
    md, png = report(result, output)
    print(md.read_text())
    print(f"wrote {output}, {md}, {png}")
