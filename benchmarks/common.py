"""What the benchmark scripts share: the repository's paths, writing a results page (JSON, Markdown, PNG), and the
way to the builders they share with the tests.

Scripts import it as `common` (they run as `python benchmarks/<name>.py`, whose folder Python puts first on the
path). The builders (the tiny synthetic sample, LAS files, a folder's state, the real sweeps, a simulated drive,
the old shell mesher, the hostile-input cases) live in tests/ (tests/builders.py, tests/meshing_reference.py,
tests/hostile/), because the rule runs one way: tests never import benchmarks/, benchmarks may import the tests'
builders. Importing this module puts tests/ on the path; a benchmark imports from there only those builders,
which import neither pytest nor any other module of tests/ (tests/test_layering.py checks both directions)."""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, Callable

REPO = Path(__file__).resolve().parents[1]
TESTS = REPO / "tests"
if str(TESTS) not in sys.path:
    sys.path.append(str(TESTS))


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
