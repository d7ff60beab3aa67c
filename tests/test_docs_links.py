"""The user guide's pages link to files that exist, and every figure they quote from a results page is on that page:
a link, an image, a path or a number that drifts from the tree fails here."""
import re
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PAGES = ["README.md", "MODEL_CARD.md", "CHANGELOG.md", "hgca_core/weights/MODEL_CARD.md", "tests/data/real/README.md",
         *sorted(str(p.relative_to(REPO)) for p in (REPO / "docs").rglob("*.md")),
         *sorted(str(p.relative_to(REPO)) for p in (REPO / "benchmarks/results").glob("*.md"))]
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")          # [text](target) and ![alt](image)
IMAGE = re.compile(r"!\[[^\]]*\]\(([^)\s]+)\)|<img [^>]*src=\"([^\"]+)\"")
# a path into the repository named in the text (a command's file, a recipe): `tests/data/real/simple.laz`
PATH = re.compile(r"(?<![\w/.<{:-])((?:tests|hgca_core|hgca_blender|docs|benchmarks|scripts)/[\w./*-]*[\w*])(?![{\w])")


def tracked() -> set[str] | None:
    """The files git tracks (a link to a file only this checkout has would break in a clone), or None outside git."""
    try:
        out = subprocess.run(["git", "-C", str(REPO), "ls-files", "-z"], capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    files = {f for f in out.decode().split("\0") if f}
    return files | {str(Path(f).parent) for f in files} | {str(p) for f in files for p in Path(f).parents}


TRACKED = tracked()


def _in_tree(path: Path) -> bool:
    """The path (or, with *, something it matches) exists here and, in a git checkout, is in the tree."""
    matches = list(REPO.glob(str(path.relative_to(REPO)))) if "*" in str(path) else [path] if path.exists() else []
    return bool(matches) and (TRACKED is None or any(str(m.resolve().relative_to(REPO)) in TRACKED for m in matches))


@pytest.mark.parametrize("page", PAGES)
def test_relative_links_resolve(page):
    text = (REPO / page).read_text()
    missing = [t for t in LINK.findall(text) if "://" not in t and not t.startswith("mailto:")
               and not _in_tree(((REPO / page).parent / t).resolve())]
    assert not missing, f"{page} links what a clone lacks (missing, or not added to git): {missing}"


@pytest.mark.parametrize("page", PAGES)
def test_images_are_in_the_tree(page):
    text = (REPO / page).read_text()
    images = [a or b for a, b in IMAGE.findall(text)]
    missing = [t for t in images if "://" not in t and not _in_tree(((REPO / page).parent / t).resolve())]
    assert not missing, f"{page} shows images a clone lacks (missing, or not added to git): {missing}"


@pytest.mark.parametrize("page", ["README.md", "MODEL_CARD.md", *[p for p in PAGES if p.startswith("docs/")]])
def test_paths_the_pages_name_are_in_the_tree(page):
    """Files a reader is told to open or pass to a command (`hgca complete tests/data/real/...`) are in the tree;
    placeholders (<name>, {a,b}) are not paths."""
    text = (REPO / page).read_text()
    missing = sorted({m for m in PATH.findall(text) if not _in_tree((REPO / m.rstrip(".")).resolve())})
    assert not missing, f"{page} names paths a clone lacks (missing, or not added to git): {missing}"


def test_the_checks_can_fail(tmp_path):
    assert LINK.findall("see [a](docs/nope.md) and ![b](img/x.png)") == ["docs/nope.md", "img/x.png"]
    assert not _in_tree(REPO / "docs/nope.md") and _in_tree(REPO / "docs/cli.md")
    assert _in_tree(REPO / "hgca_core/examples/street_scan*.laz") and not _in_tree(REPO / "hgca_core/examples/x*.laz")
    assert PATH.findall("run `hgca info tests/data/real/simple.laz`.") == ["tests/data/real/simple.laz"]
    assert PATH.findall("`7f06b18:scripts/gone.sh`, benchmarks/<name>.py, a/tests/x") == []


def test_the_user_guide_pages_exist():
    for name in ("blender", "cli", "formats", "drives", "free-space", "training", "performance", "architecture"):
        assert (REPO / "docs" / f"{name}.md").is_file(), name


# (page, results page, figures the page quotes from it)
QUOTED = [
    ("README.md", "benchmarks/results/real_scans.md", ["45.1", "41.0", "34.1", "6.3", "8.9", "12.3", "5.1", "4.9", "7.3"]),
    ("README.md", "hgca_core/weights/eval_test.md", ["2.70", "42.80", "5.07", "2.17", "47.88", "4.08", "2.55", "59.72",
                                                     "4.79", "2.13", "64.02", "3.83", "1.29", "64.38", "2.29"]),
    ("README.md", "benchmarks/results/speed_students.md", ["82.2", "42.3"]),
    ("README.md", "benchmarks/results/speed_preview.md", ["40.3", "17.2"]),
    ("MODEL_CARD.md", "benchmarks/results/real_scans.md", ["42.0–48.6", "38.2–43.8", "26.2–38.7", "4.7–8.6",
                                                           "7.4–10.6", "8.9–14.5"]),
    ("docs/performance.md", "benchmarks/results/completion_full_cpu.md", ["45.3"]),
    ("docs/performance.md", "benchmarks/results/speed_students.md", ["82.2", "102.1", "42.3", "49.9"]),
    ("docs/performance.md", "benchmarks/results/speed_preview.md", ["40.3", "43.4", "17.2", "19.7"]),
    ("docs/performance.md", "benchmarks/results/completion_scale_full_cpu.md", ["64.1", "2.90", "214.1", "5.31"]),
    ("docs/performance.md", "benchmarks/results/meshing_time.md", ["11.78", "12.25", "1352"]),
    ("docs/performance.md", "benchmarks/results/train_scaling.md", ["0.878", "1.138", "0.840"]),
    ("docs/performance.md", "benchmarks/results/drive_232m.md", ["445.4", "266.8"]),
    ("docs/performance.md", "benchmarks/results/drive.md", ["441.6", "317.8", "0.6552", "0.59"]),
    ("docs/performance.md", "benchmarks/results/drive_full.md", ["2403.3", "2.13", "2.26"]),
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


def md_tables(text: str) -> list[list[dict[str, str]]]:
    """Every markdown table of `text` as rows of {header: cell}."""
    tables, lines = [], text.splitlines()
    for i in range(len(lines) - 1):
        if lines[i].startswith("|") and re.fullmatch(r"\|(?:\s*:?-+:?\s*\|)+", lines[i + 1].strip()):
            head = [c.strip() for c in lines[i].strip().strip("|").split("|")]
            rows = []
            for line in lines[i + 2:]:
                if not line.startswith("|"):
                    break
                rows.append(dict(zip(head, (c.strip() for c in line.strip().strip("|").split("|")))))
            tables.append(rows)
    return tables


def first_number(cell: str) -> float:
    """'45.1 [42.0–48.6]' -> 45.1, '18.0 s' -> 18.0, '6,962' -> 6962."""
    return float(re.search(r"-?\d[\d,]*(?:\.\d+)?", cell).group(0).replace(",", ""))


def table_with(text: str, *headers: str) -> list[dict[str, str]]:
    found = [t for t in md_tables(text) if t and all(h in t[0] for h in headers)]
    assert len(found) == 1, (headers, len(found))
    return found[0]


def _readme_table(*headers: str) -> list[dict[str, str]]:
    return table_with((REPO / "README.md").read_text(), *headers)


def _page(path: str) -> str:
    text = (REPO / "README.md").read_text()
    assert f"]({path})" in text, f"README.md does not link {path}"
    return (REPO / path).read_text()


def test_readme_real_scans_table_is_its_results_page():
    """Row by row: the README's real-scan figures are the hGCA coarse rows of real_scans.md (2 m cut; whole input)."""
    page = _page("benchmarks/results/real_scans.md")
    whole = {r["input"]: r for r in table_with(page, "input", "method", "in observed empty (%) ↓", "swept (%) ↓")
             if r["method"] == "hGCA coarse"}
    cut = {r["input"]: r for r in table_with(page, "cut", "recall (%) ↑") if r["method"] == "hGCA coarse"
           and r["cut"] == "2 m"}
    rows = _readme_table("2 m cut recall ↑")
    names = {"Argoverse 2 log 7fab2350": "av2_7fab2350", "Argoverse 2 log adcf7d18": "av2_adcf7d18",
             "nuScenes LIDAR_TOP": "nuscenes_1532402927647951"}
    assert len(rows) == 3
    for row in rows:
        key = next(v for k, v in names.items() if row["input"].startswith(k))
        assert first_number(row["2 m cut recall ↑"]) == first_number(cut[key]["recall (%) ↑"]), key
        assert first_number(row["above the cut in observed empty ↓"]) == first_number(
            cut[key]["above cut in observed empty (%) ↓"]), key
        assert first_number(row["whole input in observed empty ↓"]) == first_number(
            whole[key]["in observed empty (%) ↓"]), key
        assert cut[key]["k"] == whole[key]["k"] == "12"   # the README says k = 12


def test_readme_synthetic_table_is_the_eval_page():
    page = _page("hgca_core/weights/eval_test.md")
    rows = {r["Method"]: r for r in md_tables(page)[0]}
    names = {"input": "input", "Poisson (Open3D)": "Poisson (Open3D)", "GCA (no planner)": "GCA (no planner)",
             "hGCA coarse (20 cm)": "hGCA coarse (planner)", "hGCA full (implicit)": "hGCA (implicit)"}
    readme = _readme_table("method", "ReSim min ↓")
    assert [r["method"] for r in readme] == list(names)
    for row in readme:
        for col in ("ReSim min ↓", "IoU (%) ↑", "Street CD min ↓"):
            assert row[col] == rows[names[row["method"]]][col], (row["method"], col)


@pytest.mark.parametrize("what, page", [("full stage (mesh)", "benchmarks/results/speed_students.md"),
                                        ("coarse stage (voxels) / preview (smooth)",
                                         "benchmarks/results/speed_preview.md")])
def test_readme_speed_table_is_the_bench_page(what, page):
    """The README's speed row against the page of the side-by-side timing: best is the page's old side (B), fast
    its new side (A); the wall medians and the peaks in GiB, at the default fp32 the page names."""
    text = _page(page)
    measured = {r["measure"]: r for r in table_with(text, "measure", "new (A)")}
    row = next(r for r in _readme_table("what", "`--quality best` (T1 30, T2 15)") if r["what"] == what)
    best, fast = row["`--quality best` (T1 30, T2 15)"], row["`--quality fast` (students, T1 10, T2 5)"]
    assert first_number(best) == first_number(measured["wall (s)"]["old (B)"])
    assert first_number(fast) == first_number(measured["wall (s)"]["new (A)"])
    assert f"{first_number(measured['peak RSS (MiB)']['old (B)']) / 1024:.2f} GiB" in best
    assert "fp32" in text


def test_md_tables_reads_rows():
    t = md_tables("x\n| a | b |\n|---|---:|\n| 1 | 2 [0–3] |\n\n")
    assert t == [[{"a": "1", "b": "2 [0–3]"}]] and first_number(t[0][0]["b"]) == 2.0


def readme_commands() -> list[list[str]]:
    """The `hgca ...` lines of the README's shell blocks, continuation lines joined, globs expanded in the clone."""
    import glob
    import shlex

    text = (REPO / "README.md").read_text()
    commands = []
    for block in re.findall(r"```sh\n(.*?)```", text, re.S):
        for line in block.replace("\\\n", " ").splitlines():
            words = shlex.split(line, comments=True)
            if words[:1] == ["hgca"]:
                commands.append([w2 for w in words[1:]
                                 for w2 in (sorted(glob.glob(w, root_dir=REPO)) if "*" in w else [w])])
    return commands


def test_readme_commands_parse_and_name_files_in_the_clone():
    """A newcomer runs the quick start as written, from the clone: each command and option exists, and every input
    it names is in the tree (outputs go to out/, which the block makes)."""
    from hgca_core.cli import build_parser

    commands = readme_commands()
    assert len(commands) >= 4
    for argv in commands:
        args = build_parser(argv).parse_args(argv)   # an unknown option or command exits here
        inputs = getattr(args, "scans", None) or getattr(args, "files", None) or []
        for name in [*inputs, getattr(args, "poses", None)]:
            if name:
                assert _in_tree((REPO / name).resolve()), (argv, name)
        out = getattr(args, "out", None)
        assert out is None or out.startswith("out/"), argv


def test_readme_python_quick_start_runs_from_the_clone(monkeypatch):
    """The README's Python block as written, from the clone's root: the files it reads are there and its call fits
    `hgca_core.complete_files` with settings that are config fields in range (the completion itself is stubbed: it
    takes minutes; tests/test_preview_and_quality.py runs the real call against the CLI)."""
    import inspect
    from pathlib import Path as P

    import hgca_core
    from hgca_core.config import CompletionConfig
    from hgca_core.files import complete_files, output_paths

    block = re.search(r"```python\n(.*?)```", (REPO / "README.md").read_text(), re.S).group(1)
    calls = []

    def stub(*args, **kwargs):
        bound = inspect.signature(complete_files).bind(*args, **kwargs).arguments
        CompletionConfig(**bound.get("settings", {}))   # every setting is a config field in range
        calls.append(bound)
        return output_paths(bound["out"], CompletionConfig(**bound.get("settings", {})).samples)

    monkeypatch.chdir(REPO)
    monkeypatch.setattr(hgca_core, "complete_files", stub)
    scope: dict = {}
    exec(compile(block, "README.md", "exec"), scope)
    assert len(calls) == 1 and len(block.strip().splitlines()) <= 4
    assert all(P(s).is_file() for s in calls[0]["scans"]) and P(calls[0]["poses"]).is_file()
    assert [p.name for p in scope["paths"]] == ["completion_s0.ply", "completion_s1.ply", "completion_s2.ply"]


@pytest.mark.parametrize("page", [p for p in PAGES if p.startswith("docs/") and p != "docs/cli.md"])
def test_the_guides_commands_parse(page):
    """Every `hgca ...` line of a guide page's shell blocks names a command and options that exist (its files may
    be the reader's own)."""
    import shlex

    from hgca_core.cli import build_parser

    for block in re.findall(r"```(?:sh|bash|console)\n(.*?)```", (REPO / page).read_text(), re.S):
        for line in block.replace("\\\n", " ").splitlines():
            words = shlex.split(line, comments=True)
            if words[:1] == ["torchrun"]:   # `torchrun ... -m hgca_core.cli CMD ...` runs `hgca CMD ...`
                words = ["hgca", *words[words.index("hgca_core.cli") + 1:]] if "hgca_core.cli" in words else []
            if words[:1] == ["hgca"]:
                try:
                    build_parser(words[1:]).parse_args(words[1:])
                except SystemExit:
                    pytest.fail(f"{page}: {line.strip()}")
