"""The folder ``tt designs --out DIR`` writes: one MJCF file per design and ``designs.json``.

``designs.json`` records the MJCF files the run wrote (``"files"``), so a later run over the
same folder knows which files are its own: it replaces and removes only those (a
``designs.json`` written before the record existed names its files by its designs:
``SPACE_NNNN.xml`` of design NNNN), and refuses to overwrite any other file. No file is
removed by its name's pattern.

The set is written whole or not at all: every file is first written (and fsync'ed) into a
staging folder inside DIR, then ``designs.json`` is rewritten to record the old and the new
files together, the files are renamed into place, ``designs.json`` is written with the new
designs, and only then are the old run's files the new one does not rewrite removed. A full
disk while staging leaves DIR as it was (the staging folder is removed); a crash during the
renames leaves a ``designs.json`` that owns every file there, so the next run cleans up.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from tt.kernels.errors import TTError
from tt.kernels.files import CorruptFileError, fsync_folder, read_json, write_bytes
from tt.sim.designs.base import Design, save_designs

#: The record beside the MJCF files.
RECORD = "designs.json"
#: Prefix of the staging folder (a leftover of a killed run is removed by the next run).
STAGING = ".tt-designs-staging-"


class DesignFolderError(TTError):
    """The folder holds files ``tt designs`` would overwrite but did not write."""


@dataclass
class FolderResult:
    """What `write_design_folder` did: files written and the earlier run's files removed."""

    written: list[str]
    removed: list[str]


def mjcf_name(design: Design, index: int) -> str:
    """The MJCF file name of design number `index`."""
    return f"{design.space}_{index:04d}.xml"


def recorded_files(folder: str | Path, flag: str = "--out") -> set[str]:
    """The MJCF files an earlier ``tt designs`` run recorded in ``folder/designs.json``
    (empty when there is none). A damaged record is refused (`CorruptFileError`), and so is
    a designs.json that is not a design file (`DesignFolderError`): what it owned cannot be
    told, and it would be overwritten."""
    path = Path(folder) / RECORD
    if not path.exists():
        return set()
    try:
        data = read_json(path, "design record")
    except CorruptFileError as e:
        raise CorruptFileError(
            f"{flag} {folder}: {e}; tt designs cannot tell which files there it wrote: move it "
            "away or choose another folder"
        ) from None
    if not isinstance(data, dict) or not isinstance(data.get("designs"), list):
        raise DesignFolderError(
            f"{flag} {folder}: its {RECORD} is not a design file tt wrote (no 'designs' list); "
            f"tt designs would overwrite it: move it away or choose another {flag}"
        )
    if "files" in data:
        files = data["files"]
        return {f for f in files if isinstance(f, str) and f == Path(f).name} if isinstance(files, list) else set()
    names = set()
    for i, item in enumerate(data.get("designs", [])):  # written before the record: SPACE_NNNN.xml of design NNNN
        if isinstance(item, dict) and isinstance(item.get("space"), str):
            names.add(f"{item['space']}_{i:04d}.xml")
    return names


def write_design_folder(
    designs: Sequence[Design], folder: str | Path, mjcf: Sequence[str], *, flag: str = "--out"
) -> FolderResult:
    """Write `designs` (MJCF texts `mjcf`, one each) and ``designs.json`` into `folder` (see
    the module docstring). Raises `DesignFolderError` naming `flag` when a file to be
    written exists and no earlier run recorded it; OSError (a full disk, naming the file)
    with the folder as it was."""
    folder = Path(folder)
    for left in folder.glob(STAGING + "*"):
        shutil.rmtree(left, ignore_errors=True)  # a killed run's staging folder
    owned = recorded_files(folder, flag)
    names = [mjcf_name(d, i) for i, d in enumerate(designs)]
    foreign = [n for n in names if (folder / n).exists() and n not in owned]
    if foreign:
        raise DesignFolderError(
            f"{flag} {folder} holds {foreign[0]}{f' (and {len(foreign) - 1} more)' if len(foreign) > 1 else ''}, "
            f"which no earlier `tt designs` run there wrote ({RECORD} does not list it); move it "
            f"away or choose another {flag}"
        )
    staging = folder / f"{STAGING}{uuid.uuid4().hex[:8]}"
    staging.mkdir()
    try:
        for name, text in zip(names, mjcf):
            write_bytes(staging / name, text.encode("utf-8"))
        save_designs(designs, staging / RECORD, files=names)
        fsync_folder(staging)
        # Owned during the renames: the old files and the new ones.
        _record_union(folder, sorted(owned | set(names)))
        for name in names:
            os.replace(staging / name, folder / name)
        os.replace(staging / RECORD, folder / RECORD)
        fsync_folder(folder)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    removed = sorted(n for n in owned - set(names) if (folder / n).is_file())
    for name in removed:
        (folder / name).unlink()
    return FolderResult(names, removed)


def _record_union(folder: Path, files: list[str]) -> None:
    """Rewrite ``designs.json`` to own `files` (its designs unchanged), before files move in."""
    path = folder / RECORD
    data = {"designs": []}
    if path.exists():
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError):
            pass  # recorded_files read it a moment ago
        if not isinstance(data, dict):
            data = {"designs": []}
    write_bytes(path, json.dumps({**data, "files": files}, indent=1).encode("utf-8"))


__all__ = ["DesignFolderError", "FolderResult", "RECORD", "mjcf_name", "recorded_files", "write_design_folder"]
