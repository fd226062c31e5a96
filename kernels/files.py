"""Reading and writing tt's files safely: one error naming the file for anything unreadable,
atomic fsync'ed writes, strict JSON.

Readers turn every failure of a foreign, truncated or damaged file into `CorruptFileError`,
so the user sees one line naming the file, never a library's traceback (and never numpy's
or torch's advice about loading pickles: tt's files hold no pickles and tt loads none).
Writers follow the dataset shards' protocol (`tt.tokens.store`): write beside the target,
fsync, rename in one step, fsync the folder, so a crash leaves the old file or the new one.
"""

from __future__ import annotations

import json
import math
import os
import zipfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from tt.kernels.errors import TTError


class CorruptFileError(TTError):
    """A file is truncated, damaged, empty or not the kind of file expected; the message names it."""


#: Words of library messages that advise loading pickles; such messages never reach the user.
_PICKLE_WORDS = ("pickle", "weights_only", "allow_pickle", "untrusted")


def reason(error: BaseException) -> str:
    """A short account of a library's read error, without advice about pickles."""
    text = str(error).strip().splitlines()[0] if str(error).strip() else ""
    if any(w in text.lower() for w in _PICKLE_WORDS):
        return "it holds Python objects (pickled data), which tt never writes and does not load"
    if isinstance(error, (zipfile.BadZipFile, EOFError)) or "zip" in text.lower() or "central directory" in text.lower():
        return "it is truncated or damaged (not a complete zip archive)"
    return f"{type(error).__name__}: {text}"[:300] if text else type(error).__name__


def check_readable(path: str | Path, what: str) -> Path:
    """`path` as a Path if it is a non-empty file; FileNotFoundError or `CorruptFileError` naming `what`."""
    path = Path(path)
    if path.is_dir():
        raise CorruptFileError(f"{what} {path} is a folder, not a file")
    if not path.is_file():
        raise FileNotFoundError(f"{what} {path} does not exist")
    if path.stat().st_size == 0:
        raise CorruptFileError(f"{what} {path} is empty (0 bytes)")
    return path


def read_npz(path: str | Path, what: str = "file") -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` archive, read at once (no pickles).

    what: what the file should be ("token file"), for messages. Raises FileNotFoundError or
    `CorruptFileError` naming the file and what is wrong with it.
    """
    path = check_readable(path, what)
    with open(path, "rb") as f:
        magic = f.read(6)
    if magic.startswith(b"\x93NUMPY"):
        raise CorruptFileError(f"{what} {path} is a single .npy array, not an .npz archive")
    if not magic.startswith(b"PK"):
        raise CorruptFileError(f"{what} {path} is not an .npz archive (it does not start with a zip header)")
    try:
        data = np.load(path, allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise CorruptFileError(f"{what} {path} is a single .npy array, not an .npz archive")
        with data:
            return {k: data[k] for k in data.files}
    except CorruptFileError:
        raise
    except Exception as e:  # zipfile, zlib and numpy's header parser raise a dozen unrelated types
        raise CorruptFileError(f"{what} {path} cannot be read as .npz: {reason(e)}") from None


def read_json(path: str | Path, what: str = "file") -> Any:
    """A JSON file's content; FileNotFoundError or `CorruptFileError` naming the file."""
    path = check_readable(path, what)
    try:
        return json.loads(path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as e:
        raise CorruptFileError(f"{what} {path} is not text (byte {e.start} is not UTF-8)") from None
    except json.JSONDecodeError as e:
        raise CorruptFileError(f"{what} {path} is not valid JSON: {e}") from None
    except RecursionError:
        raise CorruptFileError(f"{what} {path} nests too deeply to be one of tt's JSON files") from None
    except ValueError as e:  # an integer of more digits than Python converts
        raise CorruptFileError(f"{what} {path} is not valid JSON: {e}") from None


def scalar(data: dict, key: str, path: Path | str, what: str, kind: type = float):
    """``data[key]`` as one number (or string); `CorruptFileError` naming the file and key otherwise."""
    if key not in data:
        raise CorruptFileError(f"{what} {path} has no entry {key!r}; found {sorted(data)}")
    a = data[key]
    if a.size != 1:
        raise CorruptFileError(f"{what} {path}: entry {key!r} must hold one value, it has shape {a.shape}")
    try:
        return kind(a.reshape(()).item() if kind is not str else str(a.reshape(())))
    except (TypeError, ValueError, OverflowError):
        raise CorruptFileError(f"{what} {path}: entry {key!r} is not a {kind.__name__} ({a.dtype})") from None


def fsync_folder(folder: str | Path) -> None:
    """fsync a folder, so a rename inside it survives a crash (no-op where folders cannot be opened)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextmanager
def atomic_write(path: str | Path, mode: str = "wb") -> Iterator[Any]:
    """Open a temporary file beside `path`; on success flush, fsync and rename it to `path`.

    A crash or an exception leaves `path` as it was (the temporary file is removed on an
    exception; one left by a killed process never has `path`'s name).
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    f = open(tmp, mode)
    try:
        yield f
        f.flush()
        os.fsync(f.fileno())
        f.close()
        os.replace(tmp, path)
    except BaseException:
        f.close()
        tmp.unlink(missing_ok=True)
        raise
    fsync_folder(path.parent)


def strict_json(obj: Any) -> tuple[Any, list[str]]:
    """`obj` with every NaN / inf float replaced by None, and the paths replaced ("metrics[0].pos_err").

    Strict JSON has no NaN: Python's ``json`` writes a bare ``NaN`` that most other parsers reject.
    """
    nulls: list[str] = []

    def walk(x, where: str):
        if isinstance(x, dict):
            return {k: walk(v, f"{where}.{k}" if where else str(k)) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [walk(v, f"{where}[{i}]") for i, v in enumerate(x)]
        if isinstance(x, np.ndarray):
            return walk(x.tolist(), where)
        if isinstance(x, np.generic):
            x = x.item()
        if isinstance(x, float) and not math.isfinite(x):
            nulls.append(where)
            return None
        return x

    return walk(obj, ""), nulls


def write_json(path: str | Path, obj: dict, *, indent: int | None = 1) -> list[str]:
    """Write `obj` as strict JSON (atomically); NaN / inf become null and the file's
    ``"null_values"`` entry says which and why. Returns the paths written as null."""
    clean, nulls = strict_json(obj)
    if nulls:
        clean = dict(clean, null_values={"why": "NaN or infinite values, written as null (JSON has no NaN)",
                                         "fields": nulls[:50] + ([f"... {len(nulls) - 50} more"] if len(nulls) > 50 else [])})
    with atomic_write(path, "w") as f:
        f.write(json.dumps(clean, indent=indent, allow_nan=False))
    return nulls


def prepare_output(path: str | Path, flag: str, *, folder: bool = False) -> Path:
    """Create the folder an output goes to, before any work; `TTError` naming `flag` if it cannot be.

    folder: `path` is itself a folder (created); else a file whose parent folder is created
    and which must not be an existing folder.
    """
    path = Path(path)
    target = path if folder else path.parent
    if not folder and path.is_dir():
        raise TTError(f"{flag} {path} is a folder; give a file name")
    if folder and path.exists() and not path.is_dir():
        raise TTError(f"{flag} {path} is a file; give a folder")
    try:
        target.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise TTError(f"{flag} {path}: cannot create folder {target} (a file is in the way)") from None
    except PermissionError:
        raise TTError(f"{flag} {path}: no permission to create folder {target}") from None
    if not os.access(target, os.W_OK):
        raise TTError(f"{flag} {path}: folder {target} is not writable")
    return path


__all__ = ["CorruptFileError", "atomic_write", "check_readable", "fsync_folder", "prepare_output", "read_json",
           "read_npz", "reason", "scalar", "strict_json", "write_json"]
