"""Write docs/cli.md, the command reference, from the `hgca` argparse help itself, so it cannot drift.

    .venv/bin/python scripts/cli_docs.py            # rewrite docs/cli.md
    .venv/bin/python scripts/cli_docs.py --check    # exit 1 if docs/cli.md differs from what the help says now

tests/test_cli_docs.py runs the check, so a changed option or help text fails the tests until this is re-run.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "docs" / "cli.md"
WIDTH = 100   # the help's line width: fixed, so the page does not depend on the terminal that wrote it

HEADER = """# Command reference

Every `hgca` command with its full help, as `hgca COMMAND --help` prints it. This page is generated from the
command line's own definitions by `scripts/cli_docs.py`; do not edit it by hand.

Every command reports bad input as one `hgca COMMAND: error: ...` line on stderr with exit status 2 and writes
nothing; Ctrl-C or SIGTERM stops a command within about 2 s (exit 130 / 143) without leaving partial outputs.
Set `HGCA_DEBUG=1` to also print the Python traceback of an unexpected failure.

`-o/--out` is where a command writes, and its placeholder says what it is: `DIR` is a folder the command creates
and writes several files into (`drive`, `demo`, `bench`, `synth`, `train`); anything else is one file's path
(`complete -o MESH` writes MESH_s<i>.<format> per sample, `read -o FILE.npz`, `poses`, `eval` and `eval-real`
`-o FILE.json`). `complete` and `drive` take the mesh format from `--mesh-format` (`complete`: else from MESH's
extension). The defaults of the completion options are one set, `hgca_core.config.CompletionConfig`.

"""


def _help(parser: argparse.ArgumentParser) -> str:
    return parser.format_help().rstrip() + "\n"


def render() -> str:
    os.environ["COLUMNS"] = str(WIDTH)   # argparse reads the width from the environment when it formats
    sys.path.insert(0, str(REPO))
    from hgca_core.cli import COMMANDS, build_parser

    parts = [HEADER, "## hgca\n", "```text\n" + _help(build_parser([])) + "```\n"]
    parts.append("Commands: " + ", ".join(f"[`{n}`](#hgca-{n})" for n in COMMANDS) + ".\n")
    for name in COMMANDS:
        parser = build_parser([name])   # loads only this command's options, as `hgca NAME` does
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[name]
        parts += [f"\n## hgca {name}\n", f"{COMMANDS[name][0].upper()}{COMMANDS[name][1:]}.\n",
                  "```text\n" + _help(sub) + "```\n"]
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="compare with docs/cli.md instead of writing it")
    p.add_argument("--out", type=Path, default=OUT, help="the page to write or check (default docs/cli.md)")
    args = p.parse_args(argv)
    text = render()
    if args.check:
        if not args.out.is_file() or args.out.read_text() != text:
            print(f"{args.out} is out of date: run `.venv/bin/python scripts/cli_docs.py`", file=sys.stderr)
            return 1
        return 0
    args.out.write_text(text)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
