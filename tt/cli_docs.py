"""docs/cli.md: every command's ``--help``, rendered from the CLI itself, and after it the part
of the command's docstring that ``--help`` leaves out (after ``\\f``: the options in full).

The page is generated, never edited by hand: ``python -m tt.cli_docs`` rewrites it, and
``tests/test_cli_docs.py`` fails when the committed page differs from what the CLI prints
now (a changed option or help text), naming this command. Help is rendered with typer's
test runner at a fixed width (`WIDTH` columns, no colour), so the page is the same on every
machine with the pinned typer and rich (`constraints.txt`).
"""

from __future__ import annotations

import sys
from pathlib import Path

#: Terminal width the help is rendered at [columns].
WIDTH = 100
#: The page, relative to the repository root.
PAGE = Path("docs") / "cli.md"
#: The command that rewrites the page (named in the page and in the test's message).
REGENERATE = "python -m tt.cli_docs"


def command_paths() -> list[tuple[str, ...]]:
    """Every command of ``tt`` as its words after ``tt`` (``()`` is ``tt`` itself), in the
    order ``tt --help`` lists them, sub-commands after their group."""
    import typer.main

    from tt.cli import app

    root = typer.main.get_command(app)
    paths: list[tuple[str, ...]] = []

    def walk(cmd, path: tuple[str, ...]) -> None:
        paths.append(path)
        sub = getattr(cmd, "commands", None)
        if sub is None:
            return
        ctx = cmd.make_context("tt", [], resilient_parsing=True)
        for name in cmd.list_commands(ctx):
            walk(cmd.get_command(ctx, name), path + (name,))

    walk(root, ())
    return paths


def render_help(path: tuple[str, ...]) -> str:
    """``tt PATH --help`` as a terminal `WIDTH` columns wide shows it, trailing blanks removed."""
    import typer.rich_utils as rich_utils
    from typer.testing import CliRunner

    from tt.cli import app

    saved = rich_utils.MAX_WIDTH, rich_utils.FORCE_TERMINAL
    rich_utils.MAX_WIDTH, rich_utils.FORCE_TERMINAL = WIDTH, False  # read when each help is printed
    try:
        env = {"COLUMNS": str(WIDTH), "TERMINAL_WIDTH": str(WIDTH), "NO_COLOR": "1", "FORCE_COLOR": None}
        res = CliRunner().invoke(app, [*path, "--help"], prog_name="tt", env=env, terminal_width=WIDTH)
    finally:
        rich_utils.MAX_WIDTH, rich_utils.FORCE_TERMINAL = saved
    if res.exit_code != 0:
        raise RuntimeError(f"`tt {' '.join(path)} --help` exited with {res.exit_code}: {res.output}")
    lines = [line.rstrip() for line in res.output.splitlines()]
    while lines and not lines[0]:
        lines.pop(0)
    while lines and not lines[-1]:
        lines.pop()
    return "\n".join(lines)


def page() -> str:
    """The whole of docs/cli.md."""
    paths = command_paths()
    out = [
        "# The `tt` command line",
        "",
        f"Generated from the CLI by `{REGENERATE}` (each command's `--help` at {WIDTH} columns, then the options",
        "that `--help` shortens, in full); do not edit by hand. `tests/test_cli_docs.py` checks that this page",
        "matches the CLI. `tt -v COMMAND` adds tracebacks to errors.",
        "",
        "Commands: " + ", ".join(f"[`tt {' '.join(p)}`](#{_anchor(p)})" for p in paths if p) + ".",
        "",
    ]
    for p in paths:
        out += [f"## `{' '.join(('tt',) + p)}`", "", "```text", render_help(p), "```", ""]
        more = details(p)
        if more:
            out += [more, ""]
    return "\n".join(out)


def details(path: tuple[str, ...]) -> str:
    """The part of a command's docstring after ``\\f``, which ``--help`` leaves out (click's
    convention): the options explained in full, markdown."""
    import inspect

    import typer.main

    from tt.cli import app

    cmd = typer.main.get_command(app)
    for name in path:
        cmd = cmd.commands[name]
    return inspect.cleandoc(inspect.cleandoc(cmd.help or "").partition("\f")[2])


def _anchor(path: tuple[str, ...]) -> str:
    """GitHub's anchor of the heading ``## `tt PATH` ``."""
    return "-".join(("tt",) + path)


def main(argv: list[str] | None = None) -> int:
    """Write docs/cli.md under the repository root (the folder holding pyproject.toml above
    this file), or with ``--check`` exit 1 when it differs."""
    args = sys.argv[1:] if argv is None else argv
    root = Path(__file__).resolve().parents[1]
    target = root / PAGE
    text = page()
    if "--check" in args:
        same = target.exists() and target.read_text() == text
        print(f"{PAGE} is {'up to date' if same else 'out of date: run ' + REGENERATE}")
        return 0 if same else 1
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(text)
    print(f"wrote {PAGE} ({len(text.splitlines())} lines)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
