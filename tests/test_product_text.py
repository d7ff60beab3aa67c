"""The product's text says what hgca is and does, never how it was built: no numbered rounds or sessions of work
("session 31", "round 12", "run EC", "shipped since 39", `recipe_s33.md`), no borrowed machines or their transfer
limits. Scanned: the README, docs/, both model cards, the changelog, the benchmarks and their pages, scripts/,
the build files, every comment and docstring of the core and the add-on, and the text records inside the shipped
weights files (the weights record renders them verbatim)."""
from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]

# (what it is, pattern): each names one way text narrates the work rather than the product
PATTERNS: list[tuple[str, re.Pattern[str]]] = [
    ("a numbered session, round or sprint",
     re.compile(r"\b(?:work )?(?:sessions?|rounds?|sprints?|iterations? of work)\s+#?\d+", re.I)),
    ("a numbered session as an ordinal", re.compile(r"\b(?:session|round)\s+(?:no\.?\s*)?\d+(?:st|nd|rd|th)?\b", re.I)),
    ("an ordinal session", re.compile(r"\b\d+(?:st|nd|rd|th) (?:session|round)\b", re.I)),
    ("a session's possessive", re.compile(r"\b(?:session|round) \d+'s\b", re.I)),
    ("a lettered run", re.compile(r"\brun [A-Z]{1,3}\d?\b(?! ?[a-z])")),
    ("shipped since / in a number", re.compile(r"\bshipped (?:since|in|at) (?:session |round )?\d+\b", re.I)),
    ("a session-numbered name", re.compile(r"(?:^|[/_(\s`'\"])[swr]\d{2,3}(?=[/._)\s`'\"]|$)", re.M)),
    ("a session-numbered name", re.compile(r"\b(?:recipe|runs?|probe|notes?)_s\d+\b", re.I)),
    ("a session-numbered page", re.compile(r"[\w-]_s\d+\.(?:md|json|log)\b")),
    ("a borrowed machine", re.compile(r"\b(?:borrowed|lent|loaned|on loan)\b[^.\n]{0,40}"
                                      r"\b(?:GPU|machine|device|H200|H100)s?\b"
                                      r"|\b(?:GPU|machine|device)s? (?:loans?|leases?)\b", re.I)),
    ("a transfer limit", re.compile(r"\btransfer (?:limits?|caps?|budget)\b|\bat most \d+ MiB beside\b"
                                    r"|\b\d+ MiB (?:beside|that travels?|carried)\b", re.I)),
    ("device time of a loan", re.compile(r"\b(?:device|GPU) (?:time|minutes) (?:left|budget)\b|\bbudget_left\b", re.I)),
]


def product_files() -> list[Path]:
    """The text a user reads: documentation, result pages and the source of the core and the add-on."""
    files = [ROOT / name for name in ("README.md", "MODEL_CARD.md", "CHANGELOG.md", "hgca_core/weights/MODEL_CARD.md")]
    files += sorted(p for p in (ROOT / "docs").rglob("*") if p.suffix in (".md", ".json", ".txt"))
    files += sorted((ROOT / "benchmarks/results").glob("*.md")) + sorted((ROOT / "benchmarks").glob("*.py"))
    files += sorted(p for p in (ROOT / "scripts").glob("*") if p.is_file())
    files += [ROOT / name for name in ("Makefile", "pyproject.toml", "blender_manifest.toml", "tests/data/real/README.md")]
    for package in ("hgca_core", "hgca_blender"):
        files += sorted(p for p in (ROOT / package).rglob("*.py") if "__pycache__" not in p.parts)
    return [p for p in files if p.is_file()]


def findings(name: str, text: str) -> list[str]:
    """'name:line: what: the match' for every pattern hit in `text`."""
    found = []
    for what, pattern in PATTERNS:
        for m in pattern.finditer(text):
            line = text.count("\n", 0, m.start()) + 1
            found.append(f"{name}:{line}: {what}: {m.group(0).strip()!r}")
    return found


def record_strings(x, path: str = "meta"):
    """(where, text) of every string in a weights file's record, the sample file names aside."""
    if isinstance(x, dict):
        for k, v in x.items():
            if k not in ("train_samples", "history_tail"):
                yield from record_strings(v, f"{path}.{k}")
    elif isinstance(x, (list, tuple)):
        for i, v in enumerate(x):
            yield from record_strings(v, f"{path}[{i}]")
    elif isinstance(x, str):
        yield path, x


def test_patterns_catch_the_ways_history_was_told():
    """Each pattern hits what it is for and leaves ordinary product text alone, so a clean scan means something."""
    told = ["coarse.pt of session 33", "session 31's run EC at step 5,831", "shipped since 39", "in round 12",
            "benchmarks/results/recipe_s33.md", "runs/s31/ec", "checkpoints/coarse_w38.pt", "sessions 11-12",
            "a borrowed H200 GPU", "at most 64 MiB beside it", "the machine's transfer limit", "the 12th session",
            "benchmarks/results/mesh_quality_s5.md"]
    for text in told:
        assert findings("x", text), text
    ordinary = ["each session ended 2026-11-24: 12810 steps", "over 3 session(s)", "data/s6a + data/s7a",
                "a 64 MiB mmap threshold", "run on an existing Ray cluster", "a later run may add cut levels",
                "Run the model on an NVIDIA GPU", "seeds 0-11, k = 12", "round to 3 decimals", "--stride 25.6",
                "demo_out/completion_s0.png", "tiles/<i>_s<k>.ply"]
    for text in ordinary:
        assert not findings("x", text), (text, findings("x", text))


def test_product_text_does_not_narrate_how_it_was_built():
    found = []
    for path in product_files():
        found += findings(str(path.relative_to(ROOT)), path.read_text(errors="replace"))
    assert not found, "the product's text narrates its history:\n" + "\n".join(found)


@pytest.mark.parametrize("name", sorted(p.name for p in (ROOT / "hgca_core/weights").glob("*.pt")))
def test_shipped_weights_records_do_not_narrate_how_they_were_built(name):
    """The records inside the shipped files describe data, steps, recipe and blend, and name no folder of the
    machine they were trained on (paths are relative to the repository)."""
    meta = torch.load(ROOT / "hgca_core/weights" / name, map_location="cpu", weights_only=True)["meta"]
    found = []
    for where, text in record_strings(meta):
        found += findings(f"{name} {where}", text)
        if re.search(r"(?:^|[\s(])/(?:work|home|tmp|root|mnt)/", text):
            found.append(f"{name} {where}: a machine's absolute path: {text!r}")
    assert not found, "\n".join(found)
