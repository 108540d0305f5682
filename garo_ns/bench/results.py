"""Reading benchmark results, and writing one: the JSON, then its Markdown table and plot next to it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple


def publish(result: Dict[str, Any], output: Path, report: Callable[[Dict[str, Any], Path], Tuple[Path, Path]]) -> None:
    """Write `result` to `output` (JSON), then `report(result, output)`'s table and plot; print the table."""
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(json.dumps(result, indent=2))
    md, png = report(result, output)
    print(md.read_text())
    print(f"wrote {output}, {md}, {png}")


def save_figure(fig: Any, output: Path) -> Path:
    """Save a report's plot next to its JSON (`output` with .png) and close it; returns the path."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    png = output.with_suffix(".png")
    fig.savefig(png, dpi=120)
    plt.close(fig)
    return png


def read_results(paths: Sequence[Path]) -> List[Tuple[str, Dict[str, Any]]]:
    """(file name, content) of each benchmark result JSON; exits with a clear message on an unreadable one."""
    loaded = []
    for path in paths:
        try:
            loaded.append((Path(path).name, json.loads(Path(path).read_text())))
        except (OSError, json.JSONDecodeError) as err:
            raise SystemExit(f"error: cannot read benchmark result {path}: {err}") from None
    return loaded


def cell(value: Optional[float], spec: str) -> str:
    """A table's cell: `value` formatted by `spec`, or a dash where there is none."""
    return "-" if value is None else format(value, spec)
