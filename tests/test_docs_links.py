"""The user guide's pages link to files that exist, and every figure they quote from a results page is on that page:
a link or a number that drifts from the tree fails here."""
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PAGES = ["README.md", "MODEL_CARD.md", "CHANGELOG.md", *sorted(str(p.relative_to(REPO))
                                                               for p in (REPO / "docs").glob("*.md"))]
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")


@pytest.mark.parametrize("page", PAGES)
def test_relative_links_resolve(page):
    text = (REPO / page).read_text()
    missing = [t for t in LINK.findall(text) if "://" not in t and not (REPO / page).parent.joinpath(t).exists()]
    assert not missing, missing


def test_the_user_guide_pages_exist():
    for name in ("blender", "cli", "formats", "drives", "free-space", "training", "performance", "architecture"):
        assert (REPO / "docs" / f"{name}.md").is_file(), name


# (page, results page, figures the page quotes from it)
QUOTED = [
    ("README.md", "benchmarks/results/real_scans.md", ["45.1", "41.0", "34.1", "6.3", "8.9", "12.3", "5.1", "4.9", "7.3"]),
    ("README.md", "hgca_core/weights/eval_test.md", ["2.70", "42.80", "5.07", "2.17", "47.88", "4.08", "2.55", "59.72",
                                                     "4.79", "2.13", "64.02", "3.83", "1.29", "64.38", "2.29"]),
    ("README.md", "benchmarks/results/completion_coarse_cpu.md", ["18.0", "1.63"]),
    ("README.md", "benchmarks/results/completion_full_cpu.md", ["45.3", "2.55"]),
    ("MODEL_CARD.md", "benchmarks/results/real_scans.md", ["42.0–48.6", "38.2–43.8", "26.2–38.7", "4.7–8.6",
                                                           "7.4–10.6", "8.9–14.5"]),
    ("docs/performance.md", "benchmarks/results/completion_full_cpu.md", ["45.3", "15.78", "18.77", "2.85", "7.32"]),
    ("docs/performance.md", "benchmarks/results/completion_scale_full_cpu.md", ["64.1", "2.90", "214.1", "5.31"]),
    ("docs/performance.md", "benchmarks/results/meshing_time.md", ["4.35", "5.76", "8.07"]),
    ("docs/performance.md", "benchmarks/results/train_scaling.md", ["0.878", "1.138", "0.840"]),
    ("docs/performance.md", "benchmarks/results/drive.md", ["445.4", "266.8"]),
]


@pytest.mark.parametrize("page, source, figures", QUOTED)
def test_quoted_figures_are_on_their_results_page(page, source, figures):
    """Both on the results page a benchmark wrote and on the page that quotes it (en dashes: the page's ranges)."""
    text, results = (REPO / page).read_text(), (REPO / source).read_text()
    assert Path(source).name in text or source in text, f"{page} does not link {source}"
    for figure in figures:
        assert figure in results, f"{figure} not on {source}"
        assert any(_shown(form, text) for form in _roundings(figure.replace("–", "-"))), f"{figure} not on {page}"


def _roundings(figure: str) -> set[str]:
    """'15.78' -> {'15.78', '15.8', '16'}: the page may quote a figure to fewer decimals, never a different one."""
    parts = figure.split("-")
    decimals = max(len(p.split(".")[1]) if "." in p else 0 for p in parts)
    return {"-".join(f"{float(p):.{d}f}" for p in parts) for d in range(decimals + 1)} | {figure}


def _shown(form: str, text: str) -> bool:
    return re.search(rf"(?<![\d.]){re.escape(form)}(?![\d]|\.\d)", text) is not None


def test_roundings_accept_fewer_decimals_only():
    assert _roundings("15.78") == {"15.78", "15.8", "16"}
    assert _shown("15.8", "coarse 15.8 s") and not _shown("15.8", "coarse 115.8 s") and not _shown("5.8", "15.8")
    assert not any(_shown(f, "took 15.7 s") for f in _roundings("15.78"))
