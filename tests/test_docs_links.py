"""Every link in README.md and docs/ resolves inside the repository.

A relative link must name a file or folder that exists in the repository (its ``#anchor``
aside); no link may leave the repository: no ``http(s)://`` or other scheme, no absolute
path, no path that climbs above the root (``../shared/...``). Links inside code blocks and
code spans are text, not links, and are not checked.
"""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Inline links and images, ``[text](target)`` / ``![alt](target "title")``.
_INLINE = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(\s*<?([^)\s>]*)>?(?:\s+\"[^\"]*\")?\s*\)")
#: Reference definitions, ``[label]: target``.
_REFERENCE = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s|$)", re.M)


def pages() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def links(text: str) -> list[str]:
    """The link targets of a markdown text, code blocks and code spans left out."""
    text = re.sub(r"^(```|~~~).*?^\1[^\n]*$", "", text, flags=re.S | re.M)
    text = re.sub(r"(`+)(?:(?!\1).)+?\1", "", text, flags=re.S)
    return _INLINE.findall(text) + _REFERENCE.findall(text)


def problems(page: Path, root: Path = ROOT) -> list[str]:
    """What is wrong with each link of `page` (a file under `root`), one line each."""
    out = []
    for target in links(page.read_text()):
        where = f"{page.relative_to(root)}: {target!r}"
        if not target or target.startswith("#"):
            continue  # a heading of the same page
        if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target) or target.startswith("//"):
            out.append(f"{where} leaves the repository (a URL); link a page of the repository instead")
            continue
        if target.startswith("/"):
            out.append(f"{where} is an absolute path; use a path relative to the page")
            continue
        path = (page.parent / target.split("#", 1)[0]).resolve()
        if root != path and root not in path.parents:
            out.append(f"{where} points outside the repository")
        elif not path.exists():
            out.append(f"{where} does not exist")
    return out


def test_every_link_resolves_inside_the_repository():
    found = [p for page in pages() for p in problems(page)]
    assert not found, "\n".join(found)


def test_no_page_names_a_path_outside_the_repository():
    """Not even as text: a reader cannot follow `../shared/...` from a clone."""
    found = [
        f"{page.relative_to(ROOT)}:{i}"
        for page in pages()
        for i, line in enumerate(page.read_text().splitlines(), 1)
        if "../shared" in line
    ]
    assert not found, f"pages name ../shared, which is not in the repository: {found}"


def test_the_checker_sees_bad_links(tmp_path):
    text = (
        "[a](missing.md) [b](../../outside.md) [c](https://example.com) ![d](/abs.png) "
        "[ok](../README.md#top) `[code](nowhere.md)`\n\n```\n[block](nowhere.md)\n```\n[e]: also_missing.md\n"
    )
    assert links(text) == [
        "missing.md",
        "../../outside.md",
        "https://example.com",
        "/abs.png",
        "../README.md#top",
        "also_missing.md",
    ], links(text)
    (tmp_path / "README.md").write_text("")
    probe = tmp_path / "docs" / "p.md"
    probe.parent.mkdir()
    probe.write_text(text)
    found = problems(probe, root=tmp_path.resolve())
    assert len(found) == 5 and not any("README" in m for m in found), found
