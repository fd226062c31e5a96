"""docs/cli.md is the CLI's own help: the committed page equals what `python -m tt.cli_docs` writes."""

from pathlib import Path

from tt.cli_docs import PAGE, REGENERATE, command_paths, page

ROOT = Path(__file__).resolve().parents[1]


def test_cli_page_matches_the_cli():
    committed = (ROOT / PAGE).read_text() if (ROOT / PAGE).exists() else ""
    generated = page()
    if committed != generated:
        old, new = committed.splitlines(), generated.splitlines()
        first = next((i for i, (a, b) in enumerate(zip(old, new)) if a != b), min(len(old), len(new)))
        raise AssertionError(
            f"{PAGE} is out of date with the CLI (first difference at line {first + 1}: "
            f"{old[first] if first < len(old) else '<end>'!r} vs {new[first] if first < len(new) else '<end>'!r}); "
            f"regenerate it with `{REGENERATE}` and commit it"
        )


def test_cli_page_holds_every_command():
    text = (ROOT / PAGE).read_text()
    paths = command_paths()
    assert ("optimize",) in paths and ("dataset", "info") in paths, paths
    for p in paths:
        assert f"## `{' '.join(('tt',) + p)}`" in text, p


def test_optimize_help_shows_the_common_path_in_80_lines():
    """`tt optimize --help` at 100 columns fits 80 lines: the common options first, the model's,
    the search's and the paper ablations' in their own panels, long explanations in docs/cli.md."""
    from tt.cli_docs import WIDTH, details, render_help

    assert WIDTH == 100
    text = render_help(("optimize",))
    lines = text.splitlines()
    assert len(lines) <= 80, f"`tt optimize --help` is {len(lines)} lines at 100 columns:\n{text}"
    panels = [line for line in lines if line.startswith("╭─")]
    assert [p.split("─ ")[1].split(" ─")[0] for p in panels] == [
        "Options",
        "Model (learned methods)",
        "Search and rollout",
        "Advanced / paper ablations",
    ], panels
    assert "--config" in details(("optimize",)), "the options in full follow the help in docs/cli.md"


def _options() -> dict[str, list[str]]:
    """Every command's options by click introspection: each leaf command's parameters that are
    options (--help aside), and the root `tt`'s own."""
    import typer.main

    from tt.cli import app

    out: dict[str, list[str]] = {}

    def walk(cmd, path: tuple[str, ...]) -> None:
        sub = getattr(cmd, "commands", None)
        if not path or sub is None:
            out[" ".join(("tt",) + path)] = [
                p.opts[0] for p in cmd.params if p.param_type_name == "option" and p.name != "help"
            ]
        if sub is not None:
            ctx = cmd.make_context("tt", [], resilient_parsing=True)
            for name in cmd.list_commands(ctx):
                walk(cmd.get_command(ctx, name), path + (name,))

    walk(typer.main.get_command(app), ())
    return out


def test_the_cli_has_at_most_90_options():
    """Issue 52: at least 40 % fewer options than the 151 of its baseline (154 before the cut).
    The research settings live in --config (a file or KEY=VALUE), validated by the configs."""
    options = _options()
    total = sum(len(v) for v in options.values())
    assert total <= 90, {k: len(v) for k, v in options.items()}
    assert options["tt optimize"][-1] == "--config" and "--config" in options["tt train"]
