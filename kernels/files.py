"""Reading and writing tt's files safely: one error naming the file for anything unreadable,
atomic fsync'ed writes, strict JSON.

Readers turn every failure of a foreign, truncated or damaged file into `CorruptFileError`,
so the user sees one line naming the file, never a library's traceback (and never numpy's
or torch's advice about loading pickles: tt's files hold no pickles and tt loads none).
Writers follow the dataset shards' protocol (`tt.tokens.store`): write beside the target,
fsync, rename in one step, fsync the folder, so a crash leaves the old file or the new one.
`atomic_write` is the one writer of every file tt writes where the user said (``--json``,
``--out``, ``--html``, ``--png``, ...): ``-`` means stdout, a symbolic link is written
through to its target (the link stays), a character device or pipe (``/dev/stdout``,
``/dev/null``, a FIFO) is written into, and other non-regular targets are refused naming
the flag. A failed write (a full disk) leaves the old file whole and removes the temporary
one, and its error names the file.
"""

from __future__ import annotations

import io
import json
import math
import os
import secrets
import stat
import sys
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


def _is_pickle(path: str | Path) -> bool:
    """Whether file `path` starts as a pickle of protocol 2 or later does (PROTO opcode)."""
    try:
        with open(path, "rb") as f:
            head = f.read(2)
    except OSError:
        return False
    return len(head) == 2 and head[0] == 0x80 and 2 <= head[1] <= 5


def reason(error: BaseException, path: str | Path | None = None) -> str:
    """A short account of a library's read error, without advice about pickles.

    path: the file read; with it, an error about pickles (torch reads any file that is not a
    zip archive as a pickle) is said to be pickled data only when the file starts as a
    pickle does, and random bytes are said to be no file tt wrote."""
    text = str(error).strip().splitlines()[0] if str(error).strip() else ""
    if any(w in text.lower() for w in _PICKLE_WORDS):
        if path is not None and not _is_pickle(path):
            try:
                with open(path, "rb") as f:
                    head = f.read(4).hex(" ")
            except OSError:
                head = "?"
            return (
                f"it is no file tt wrote: neither a zip archive (torch.save's format) nor pickled data (its first "
                f"bytes are {head})"
            )
        return "it holds Python objects (pickled data), which tt never writes and does not load"
    if (
        isinstance(error, (zipfile.BadZipFile, EOFError))
        or "zip" in text.lower()
        or "central directory" in text.lower()
    ):
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


#: The output path that means standard output.
STDOUT = "-"


def is_stdout(path: str | Path | None) -> bool:
    """Whether output `path` is ``-``, standard output."""
    return path is not None and str(path) == STDOUT


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISBLK, "block device"), (stat.S_ISSOCK, "socket"), (stat.S_ISDIR, "folder")):
        if test(mode):
            return name
    return "special file"


def output_target(path: str | Path, flag: str | None = None) -> tuple[str, Path]:
    """How output `path` is written: ``("stdout", path)`` for ``-`` or a path that is this
    process's stdout (``/dev/stdout``); ``("stream", path)`` for a character device or a pipe
    (``/dev/null``, a FIFO), written into as it is; ``("file", target)`` for a regular file
    or a new one, `target` being the file a symbolic link (chain) points to, which is
    replaced while the link stays. A folder, a block device or a socket is refused
    (`TTError` naming `flag`)."""
    name = flag or "output"
    if is_stdout(path):
        return "stdout", Path(STDOUT)
    p = Path(path)
    try:
        st = os.stat(p)
    except (FileNotFoundError, NotADirectoryError):
        st = None
    if st is None:
        # A new file, or a dangling link: the file is created where the link points.
        return "file", Path(os.path.realpath(p)) if p.is_symlink() else p
    try:
        if os.path.samestat(st, os.fstat(sys.stdout.fileno())):
            return "stdout", p
    except (AttributeError, OSError, ValueError, io.UnsupportedOperation):
        pass  # a stdout with no file descriptor (a test runner's buffer)
    if stat.S_ISDIR(st.st_mode):
        raise TTError(f"{name} {path} is a folder; give a file name")
    if stat.S_ISCHR(st.st_mode) or stat.S_ISFIFO(st.st_mode):
        return "stream", p
    if not stat.S_ISREG(st.st_mode):
        raise TTError(f"{name} {path} is a {_kind(st.st_mode)}, not a file; give a file name (or - for stdout)")
    return "file", Path(os.path.realpath(p))


def _named(e: OSError, path: str | Path) -> OSError:
    """`e` with the file it concerns (a write's error names none)."""
    if e.filename is not None or e.errno is None:
        return e
    return OSError(e.errno, e.strerror or str(e), str(path))


def _to_stdout(data: bytes | str) -> None:
    out = sys.stdout
    if isinstance(data, bytes):
        out.flush()
        out.buffer.write(data)
        out.buffer.flush()
    else:
        out.write(data)
        out.flush()


@contextmanager
def atomic_write(path: str | Path, mode: str = "wb", *, flag: str | None = None) -> Iterator[Any]:
    """Open a temporary file beside `path`; on success flush, fsync and rename it to `path`.

    A crash or an exception leaves `path` as it was (the temporary file is removed on an
    exception; one left by a killed process never has `path`'s name). An OSError of the
    write (a full disk) names `path`. The file is what `output_target` says: ``-`` (or
    ``/dev/stdout``) goes to stdout and a character device or pipe is written into, each
    once the content is complete; a symbolic link is written through (its target is
    replaced, with the target's permissions); `flag` names the option in refusals.
    Text modes write UTF-8.
    """
    kind, target = output_target(path, flag)
    binary = "b" in mode
    if kind != "file":
        buf = io.BytesIO() if binary else io.StringIO()
        yield buf
        try:
            if kind == "stdout":
                _to_stdout(buf.getvalue())
            else:
                with open(target, "wb" if binary else "w", encoding=None if binary else "utf-8") as f:
                    f.write(buf.getvalue())
        except OSError as e:
            raise _named(e, path) from None
        return
    try:
        before = os.stat(target)
    except OSError:
        before = None
    tmp = target.with_name(f".{target.name}.tmp-{os.getpid()}-{secrets.token_hex(3)}")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    except OSError as e:
        raise _named(e, path) from None
    try:
        if before is not None:
            os.fchmod(fd, stat.S_IMODE(before.st_mode))  # replaced, not widened: keep the file's permissions
        f = os.fdopen(fd, mode, **({} if binary else {"encoding": "utf-8"}))
    except BaseException:
        os.close(fd)
        tmp.unlink(missing_ok=True)
        raise
    try:
        yield f
        f.flush()
        os.fsync(f.fileno())
        f.close()
        os.replace(tmp, target)
    except BaseException as e:
        try:
            f.close()
        except OSError:
            pass  # a full disk fails the close's flush too; the file goes anyway
        tmp.unlink(missing_ok=True)
        if isinstance(e, OSError):
            raise _named(e, path) from None
        raise
    fsync_folder(target.parent)


def write_bytes(path: str | Path, data: bytes, *, flag: str | None = None) -> None:
    """Write `data` to output `path` through `atomic_write`."""
    with atomic_write(path, "wb", flag=flag) as f:
        f.write(data)


def write_text(path: str | Path, text: str, *, flag: str | None = None) -> None:
    """Write `text` (UTF-8) to output `path` through `atomic_write`."""
    with atomic_write(path, "w", flag=flag) as f:
        f.write(text)


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


def write_json(path: str | Path, obj: dict, *, indent: int | None = 1, flag: str | None = None) -> list[str]:
    """Write `obj` as strict JSON (`atomic_write`: ``-`` is stdout); NaN / inf become null and
    the file's ``"null_values"`` entry says which and why. Returns the paths written as null."""
    clean, nulls = strict_json(obj)
    if nulls:
        clean = dict(
            clean,
            null_values={
                "why": "NaN or infinite values, written as null (JSON has no NaN)",
                "fields": nulls[:50] + ([f"... {len(nulls) - 50} more"] if len(nulls) > 50 else []),
            },
        )
    text = json.dumps(clean, indent=indent, allow_nan=False)
    write_text(path, text + "\n" if is_stdout(path) else text, flag=flag)
    return nulls


def prepare_output(path: str | Path, flag: str, *, folder: bool = False) -> Path:
    """Create the folder an output goes to, before any work; `TTError` naming `flag` if it cannot be.

    folder: `path` is itself a folder (created); else a file (``-``: stdout) whose parent
    folder is created and which must be something `atomic_write` can write (not a folder,
    a block device, ...). A symbolic link's target folder is the one created.
    """
    path = Path(path)
    if is_stdout(path):
        if folder:
            raise TTError(f"{flag} -: a folder of files cannot go to stdout; give a folder name")
        return path
    if folder:
        target = path
        if path.exists() and not path.is_dir():
            raise TTError(f"{flag} {path} is a file; give a folder")
    else:
        kind, written = output_target(path, flag)
        if kind != "file":
            return path
        target = written.parent
    try:
        target.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise TTError(f"{flag} {path}: cannot create folder {target} (a file is in the way)") from None
    except PermissionError:
        raise TTError(f"{flag} {path}: no permission to create folder {target}") from None
    if not os.access(target, os.W_OK):
        raise TTError(f"{flag} {path}: folder {target} is not writable")
    return path


__all__ = [
    "CorruptFileError",
    "STDOUT",
    "atomic_write",
    "check_readable",
    "fsync_folder",
    "is_stdout",
    "output_target",
    "prepare_output",
    "read_json",
    "read_npz",
    "reason",
    "scalar",
    "strict_json",
    "write_bytes",
    "write_json",
    "write_text",
]
