"""CI runs README's first two commands exactly as README writes them.

README opens with the two commands a new user types (install and run the main job; install
with the test extra and run the tests). `.ci/run` must run both as written, so a change to
either that breaks a fresh machine breaks CI.
"""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    block = re.search(r"^```bash\n(.*?)^```", text, flags=re.S | re.M)
    assert block, "README.md has no ```bash block"
    commands = [line.split(" #", 1)[0].strip() for line in block.group(1).splitlines()]
    return [c for c in commands if c and not c.startswith("#")]


def test_readme_opens_with_the_install_and_run_and_the_test_commands():
    commands = _readme_commands()
    assert len(commands) == 2, f"README.md's first bash block should hold two commands, holds {commands}"
    assert commands[0].startswith("pip install -e . ") and commands[0].endswith("tt demo"), commands[0]
    assert "'.[test]'" in commands[1] and "pytest" in commands[1], commands[1]


def test_ci_runs_each_readme_command_as_written():
    ci = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()]
    missing = [c for c in _readme_commands() if c not in ci]
    assert not missing, f".ci/run does not run these commands of README.md's first bash block as written: {missing}"


def test_ci_runs_the_first_command_in_a_fresh_venv():
    """The first command must meet a venv with nothing in it: no system site packages, no
    test extra installed before it."""
    ci = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()]
    first, second = _readme_commands()
    assert first in ci and second in ci, (
        "README's commands are not in .ci/run as written (test_ci_runs_each_readme_command_as_written)"
    )
    at = ci.index(first)
    venv = [i for i, line in enumerate(ci) if re.match(r"python3? -m venv ", line)]
    activate = [i for i, line in enumerate(ci) if re.match(r"(source|\.) .*/bin/activate\"?$", line)]
    assert venv and activate and venv[-1] < activate[-1] < at, (
        ".ci/run must create a venv (python -m venv) and activate it before README's first command"
    )
    assert "--system-site-packages" not in ci[venv[-1]], ci[venv[-1]]
    assert "deactivate" in ci[at + 1 : ci.index(second)], (
        ".ci/run must deactivate the fresh venv before the test command"
    )
    assert ci.index(second) > at, ".ci/run must run the first command before the test command"
