"""Every third-party module tt imports belongs to a dependency of the base install.

A fresh ``pip install -e . -c constraints.txt`` installs ``[project].dependencies`` and what
they require, nothing more: an import covered only by an extra (the ``test`` extra brings Ray
and, through it, click) or by nothing passes on a development machine and fails on a user's.
So the imports of every module of the package (top level and inside functions) are parsed
with ``ast``, each top-level module is mapped to the distribution(s) that install it, and
each of those must lie in the requirement closure of the base dependencies. The only
exceptions are the imports listed in ``OPTIONAL``, each for a feature that names its extra
when the module is missing (checked below).
"""

from __future__ import annotations

import ast
import importlib.metadata as md
import re
import sys
import tomllib
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Imports that may be missing from a base install: module -> (the extra that brings it, why).
#: Each must sit in a ``try: import ... except ImportError`` whose handler raises an error
#: naming the extra (test_optional_imports_are_guarded), and the guard is run below.
OPTIONAL = {
    "ray": (
        "ray",
        "`tt generate --ray` distributes shards over a Ray cluster; the base install runs them as processes",
    ),
}


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def _package_files() -> list[Path]:
    """The .py files of every package pyproject maps into ``tt`` (each mapped folder holds one
    package; its subpackages are mapped on their own)."""
    dirs = _pyproject()["tool"]["setuptools"]["package-dir"]
    files = sorted({f for d in dirs.values() for f in (ROOT / d).glob("*.py")})
    assert len(files) > 20, f"found only {len(files)} package files under {sorted(dirs.values())}"
    return files


def _imports(path: Path) -> list[tuple[str, int, bool]]:
    """(top-level module, line, guarded) of each absolute import in a file. Guarded: inside a
    ``try`` that catches ImportError, or later in the same function than such an import of
    the same module (``from ray.util.queue import Queue`` after a guarded ``import ray``)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    guarded: set[int] = set()  # ids of import nodes inside a try that catches ImportError
    for node in ast.walk(tree):
        if isinstance(node, ast.Try) and any(_catches_import_error(h) for h in node.handlers):
            for stmt in node.body:
                guarded |= {id(n) for n in ast.walk(stmt) if isinstance(n, (ast.Import, ast.ImportFrom))}
    for fn in ast.walk(tree):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            inside = [n for n in ast.walk(fn) if _top(n)]
            first = {}  # module -> line of its first guarded import in this function
            for n in inside:
                if id(n) in guarded:
                    for m in _top(n):
                        first[m] = min(first.get(m, n.lineno), n.lineno)
            guarded |= {id(n) for n in inside if all(m in first and n.lineno > first[m] for m in _top(n))}
    return [(m, n.lineno, id(n) in guarded) for n in ast.walk(tree) for m in _top(n)]


def _top(node: ast.AST) -> list[str]:
    """The top-level modules an import statement names (none for a relative import)."""
    if isinstance(node, ast.Import):
        return [a.name.split(".")[0] for a in node.names]
    if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
        return [node.module.split(".")[0]]
    return []


def _catches_import_error(handler: ast.ExceptHandler) -> bool:
    names = handler.type.elts if isinstance(handler.type, ast.Tuple) else [handler.type]
    return any(isinstance(n, ast.Name) and n.id in ("ImportError", "ModuleNotFoundError") for n in names)


def _third_party_imports() -> dict[str, list[tuple[str, int, bool]]]:
    """module -> [(file relative to the repository, line, guarded)], stdlib and tt left out."""
    out: dict[str, list] = defaultdict(list)
    for f in _package_files():
        for module, line, guarded in _imports(f):
            if module in sys.stdlib_module_names or module == "tt":
                continue
            out[module].append((str(f.relative_to(ROOT)), line, guarded))
    return out


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _parse(req: str) -> tuple[str, set[str], str | None]:
    """(normalised name, extras asked for, marker text or None) of a requirement string."""
    spec, _, marker = req.partition(";")
    m = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*(?:\[([^\]]*)\])?", spec)
    assert m, f"cannot parse requirement {req!r}"
    extras = {_norm(e) for e in (m.group(2) or "").split(",") if e.strip()}
    return _norm(m.group(1)), extras, marker.strip() or None


def _applies(marker: str | None, extras: set[str]) -> bool:
    """Whether a requirement with this marker is installed when its distribution is installed
    with these extras (none for the base install)."""
    if marker is None:
        return True
    try:
        from packaging.markers import Marker
    except ImportError:  # a simple reading: requirements of an extra apply only when it is asked for
        asked = re.findall(r"""extra\s*==\s*['"]([^'"]+)['"]""", marker)
        return not asked or any(_norm(e) in extras for e in asked)
    m = Marker(marker)
    return any(m.evaluate({"extra": e}) for e in (extras or {""}))


def _base_closure() -> set[str]:
    """Normalised names of the distributions a base install of tt brings: pyproject's
    ``[project].dependencies`` (what a fresh ``pip install -e .`` reads; the installed
    metadata may predate an edit) and, recursively, their requirements as installed here,
    each with the extras it was asked for and none of its other extras' requirements."""
    todo = [_parse(r) for r in _pyproject()["project"]["dependencies"]]
    todo = [(n, e) for n, e, marker in todo if _applies(marker, set())]
    seen: dict[str, set[str]] = {}
    missing = []
    while todo:
        name, extras = todo.pop()
        if name in seen and extras <= seen[name]:
            continue
        seen[name] = seen.get(name, set()) | extras
        try:
            reqs = md.requires(name) or []
        except md.PackageNotFoundError:
            missing.append(name)
            continue
        for r in reqs:
            n, e, marker = _parse(r)
            if _applies(marker, seen[name]):
                todo.append((n, e))
    declared = {_parse(r)[0] for r in _pyproject()["project"]["dependencies"]}
    assert not (set(missing) & declared), (
        f"declared dependencies not installed here: {sorted(set(missing) & declared)}; "
        "run pip install -e '.[test]' -c constraints.txt"
    )
    return set(seen)


def test_every_third_party_import_is_a_base_dependency():
    closure = _base_closure()
    dists = md.packages_distributions()
    bad = []
    for module, sites in sorted(_third_party_imports().items()):
        if module in OPTIONAL:
            continue
        owners = {_norm(d) for d in dists.get(module, [])}
        if not owners & closure:
            where = ", ".join(f"{f}:{line}" for f, line, _ in sites)
            who = f"installed by {sorted(owners)}" if owners else "installed by no distribution here"
            bad.append(f"{module} ({who}) <- {where}")
    assert not bad, (
        "modules imported by tt but not brought by pyproject.toml's [project].dependencies "
        "(declare them there and pin them in constraints.txt, or list them in OPTIONAL with "
        "a guard):\n  " + "\n  ".join(bad)
    )


def test_optional_imports_are_guarded_and_their_extras_exist():
    extras = _pyproject()["project"]["optional-dependencies"]
    imports = _third_party_imports()
    for module, (extra, _why) in OPTIONAL.items():
        assert module in imports, f"{module} is listed optional but tt no longer imports it: drop it from OPTIONAL"
        unguarded = [f"{f}:{line}" for f, line, guarded in imports[module] if not guarded]
        assert not unguarded, f"{module} is optional but imported without an ImportError guard at {unguarded}"
        assert extra in extras and any(_parse(r)[0] == _norm(module) for r in extras[extra]), (
            f"the extra {extra!r} of pyproject.toml does not bring {module}"
        )


def test_generate_without_ray_names_the_extra(monkeypatch):
    """The guard of ``tt generate --ray``: with Ray missing, the error names the flag and the
    extra that installs it."""
    from tt.generate import _run_ray

    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` now raises ImportError
    with pytest.raises(Exception) as e:
        _run_ray(None, [], None, "cpu", None, 1, "local", None)
    assert "ray" in str(e.value) and "tt[ray]" in str(e.value), str(e.value)
