"""tt's error policy: every error about user input is a `tt.TTError` (a ValueError too), which
the CLI prints as one ``error: ...`` line; anything else is a bug, shown with its traceback
and a request to report it."""

import ast
import errno
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE_DIRS = ("kernels", "sim", "tokens", "dit", "guidance", "baselines", "viz", "tt")

#: The bare ValueErrors left in the package: each guards an invariant of tt's own code or of
#: the data tt itself writes, so it fires only on a bug in tt (and the CLI shows its
#: traceback). path -> (count, why). Every error about user input is a TTError instead.
INTERNAL_VALUE_ERRORS = {
    "kernels/model.py": (2, "_struct and tree_model check the member names of field sets tt's builders make"),
    "kernels/ltdl.py": (1, "dof parents come from a MuJoCo tree, whose bodies MuJoCo orders parent first"),
    "kernels/rollout.py": (1, "the launcher is handed slices of worlds without the pool tt creates for them"),
    "kernels/generated.py": (1, "the generated kernel source lacks a function tt's generator writes"),
    "sim/designs/viperx.py": (1, "arm_parts gets the axes and lengths of a design the space has validated"),
    "sim/designs/mjcf.py": (1, "chain_xml gets one segment per joint from the spaces' builders"),
    "sim/designs/chain_tree.py": (4, "chain_fields gets arrays the space's batch builder shapes, and its template"),
    "sim/newton_backend.py": (4, "Newton's parse of the MJCF tt wrote disagrees with MuJoCo's"),
    "tokens/schema.py": (3, "the token schema's attribute definitions are tt's constants"),
    "tokens/store.py": (
        10,
        "shard parts and reads that tt's generator and loader make (shard index, row counts, blocks, dtypes)",
    ),
    "dit/ema.py": (1, "the EMA shadows the very parameters of the model it was made from"),
    "guidance/critic_grad.py": (1, "the sampler passes each candidate's simulated first step to a start-aware critic"),
}


def _bare_value_errors() -> dict[str, int]:
    counts: dict[str, int] = {}
    for folder in PACKAGE_DIRS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                exc = node.exc if isinstance(node, ast.Raise) else None
                if isinstance(exc, ast.Call):
                    exc = exc.func
                if isinstance(exc, ast.Name) and exc.id == "ValueError":
                    rel = path.relative_to(ROOT).as_posix()
                    counts[rel] = counts.get(rel, 0) + 1
    return counts


def test_only_internal_invariants_raise_a_bare_value_error():
    found = _bare_value_errors()
    allowed = {path: count for path, (count, _) in INTERNAL_VALUE_ERRORS.items()}
    assert found == allowed, (
        "a `raise ValueError` about user input must be a TTError (tt.kernels.errors) or a subclass; "
        f"only the internal invariants of INTERNAL_VALUE_ERRORS stay ValueError. found {found}, allowed {allowed}"
    )


def test_error_message_and_is_bug():
    from tt.cli import error_message, is_bug
    from tt.kernels.errors import TTError
    from tt.sim.designs import DesignError

    assert not is_bug(TTError("--n must be >= 1")) and error_message(TTError("--n must\nbe >= 1")) == "--n must be >= 1"
    assert not is_bug(DesignError("bad design"))
    assert issubclass(TTError, ValueError)  # `except ValueError` callers keep working
    missing = FileNotFoundError(errno.ENOENT, "No such file or directory", "x.json")
    assert not is_bug(missing) and error_message(missing) == "No such file or directory: x.json"
    full = OSError(errno.ENOSPC, "No space left on device", "out.npz")
    assert "free space" in error_message(full)
    assert not is_bug(MemoryError())
    for bug in (ValueError("boom"), KeyError("k"), TypeError("t"), TTError("")):
        assert is_bug(bug), bug
        assert "this is a bug in tt" in error_message(bug) and "report it" in error_message(bug)


def test_a_bug_shows_its_traceback_and_asks_for_a_report(tt_cli, tmp_path, monkeypatch):
    from tt.sim.designs import base

    def broken(self, n, seed):
        raise ValueError("an internal invariant")

    monkeypatch.setattr(base.DesignSpace, "sample", broken)
    code, out = tt_cli(["designs", "--out", str(tmp_path / "d")])
    assert code == 2 and "Traceback" in out and "ValueError: an internal invariant" in out, out
    assert "this is a bug in tt: please report it" in out, out


def test_bad_input_is_one_line_without_a_traceback(tt_cli, tmp_path):
    code, out = tt_cli(["designs", "--space", "nope", "--out", str(tmp_path / "d")])
    lines = set(out.strip().splitlines())  # the runner may show stderr twice (in output and stderr)
    assert code == 2 and len(lines) == 1 and lines.pop().startswith("error: unknown design space 'nope'"), out


@pytest.mark.parametrize("path", sorted(INTERNAL_VALUE_ERRORS))
def test_the_allow_list_says_why(path):
    count, why = INTERNAL_VALUE_ERRORS[path]
    assert count >= 1 and len(why) > 20 and (ROOT / path).exists()
