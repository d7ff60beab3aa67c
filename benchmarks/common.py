"""What every benchmark script shares: writing its results page (JSON for machines, Markdown for people, and the
PNG rendering beside the table). Imported by the scripts in this folder as `common` (they run as
`python benchmarks/<name>.py`, whose folder Python puts first on the path)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable


def write_page(folder: Path, name: str, result: dict[str, Any], page: Callable[[dict[str, Any]], str],
               plot: Callable[[dict[str, Any], Path], None] | None = None) -> str:
    """Write `name`.json, `name`.md (and `name`.png when `plot` is given) into `folder`; returns the Markdown."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{name}.json").write_text(json.dumps(result, indent=1))
    text = page(result)
    (folder / f"{name}.md").write_text(text)
    if plot is not None:
        plot(result, folder / f"{name}.png")
    return text
