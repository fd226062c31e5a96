"""RoboToken datasets on disk: a zarr v3 store of atomically written shards, and its reader.

Layout of a dataset folder ``DATASET/``::

    zarr.json               root group; attributes: format, schema_version, schema, tt_version,
                            space, config (the generating config), maxima (tokens per robot /
                            per step of the design space's largest robot), motions (names of
                            the training motions), and once every shard exists: complete,
                            normalizer (`tt.tokens.normalize.Normalizer.to_dict`), totals
    shards/sNNNNNN/         one zarr group per shard, complete or absent:
      zarr.json             attributes: index, designs, episodes, steps, length_min, length_max,
                            generated, dropped, stats (per token type: min and max of every
                            value over real tokens)
      manifest.json         size and CRC-32 of every other file of the shard (written last)
      design/               discrete (D, nd) int16 (-1 padded), continuous (D, nc) float64 (NaN padded)
      episode/              per-episode index arrays (E,): design (row in design/), step_start
                            (row in the per-step arrays), length (control steps), episode_id,
                            motion, se2 (E, 3), reward, pos_err, orn_err, survival, ...
      <embodiment type>/    values (D, L, width) float32, ids (D, L, k) int32, mask (D, L) bool
      <per-step type>/      values (S, P, width) float32 (S = sum of lengths: every executed step
                            of every episode, episode after episode), ids (E, P, k) int32 (time
                            ID left 0: it is the step index), mask (E, P) bool
    .partial/               shards being written (removed when a run starts)

L and P are the design space's maxima (`maxima`), so every shard has the same widths and a
window needs no re-padding. Types a space never has (count 0) are not stored.

Why shards are directories renamed into place: a shard is written under ``.partial/``,
its files checksummed into ``manifest.json``, fsync'ed, and the directory renamed to
``shards/sNNNNNN`` (one atomic rename), so ``shards/`` never holds a half-written shard
after a crash, and a shard damaged later (a truncated or altered file) fails `verify_shard`.

Beside it: `tt.tokens.lock` (one writer per dataset), `tt.tokens.info` (what
``tt dataset info`` reports); the writer of whole datasets is `tt.generate` (the app), the
training reader `tt.dit.loader`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shutil
import uuid
import zlib
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np

from tt.kernels.errors import TTError
from tt.kernels.files import reason
from tt.kernels.version import tt_version
from tt.tokens.schema import EMBODIMENT_TYPES, SCHEMA, SCHEMA_VERSION, check_version

logger = logging.getLogger(__name__)

#: Format tag in the root attributes; bumps when the layout above changes.
FORMAT = "tt.dataset/1"
#: Control steps per chunk of the per-step arrays (~60 ViperX episodes): big enough that a
#: block read is a few large reads, small enough that a random window reads little.
STEP_CHUNK = 16384
#: Rows per chunk of per-episode arrays, and of per-design arrays (a block reads its few
#: robots' tokens: small chunks keep that read small).
EPISODE_CHUNK = 65536
DESIGN_CHUNK = 256
#: Episodes per block: the unit the loaders read (`ShardReader.read_block`).
BLOCK_EPISODES = 64

_SHARD_RE = re.compile(r"^s(\d{6})$")
_MANIFEST = "manifest.json"


class DatasetError(TTError):
    """A dataset folder that does not exist, is of another format or config, or is incomplete."""


def shard_name(index: int) -> str:
    """Folder name of shard `index` (``s000042``)."""
    if not 0 <= index < 10**6:
        raise ValueError(f"shard index {index} is out of range 0..999999")
    return f"s{index:06d}"


def _compressor():
    from zarr.codecs import BloscCodec, BloscShuffle

    # lz4 + bitshuffle: ~1.4x on float32 physics data, and decoding is far faster than
    # reading from disk, so training reads are not compute bound.
    return BloscCodec(cname="lz4", clevel=5, shuffle=BloscShuffle.bitshuffle)


# ------------------------------------------------------------------------------ root
def is_dataset(path: str | Path) -> bool:
    """True when `path` is a folder with a tt dataset root (``zarr.json`` with our format tag)."""
    meta = Path(path) / "zarr.json"
    if not meta.is_file():
        return False
    try:
        return json.loads(meta.read_text()).get("attributes", {}).get("format") == FORMAT
    except (OSError, json.JSONDecodeError):
        return False


#: Root attributes every dataset root holds (`create_root`'s caller writes the last ones).
ROOT_KEYS = ("format", "schema_version", "space", "config", "maxima", "design_widths", "motions")


def root_damage(path: str | Path) -> str | None:
    """Why the root ``zarr.json`` of a folder holding a dataset's ``shards/`` is damaged (not
    JSON, no attributes, or lacking the dataset's keys), or None: intact, absent, or another
    format's (a foreign store is not a damaged one). `tt.generate` rebuilds a damaged root from
    the arguments that generated the shards beside it."""
    path = Path(path)
    meta = path / "zarr.json"
    if not meta.is_file() or not (path / "shards").is_dir():
        return None
    raw = meta.read_bytes()
    if not raw.strip():
        return "empty"
    try:
        data = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        return "not text: it holds binary bytes"
    except ValueError as e:
        return f"not valid JSON: {e}"
    attrs = data.get("attributes") if isinstance(data, dict) else None
    if not isinstance(attrs, dict):
        return "it holds no attributes"
    if attrs.get("format", FORMAT) != FORMAT:
        return None
    missing = [k for k in ROOT_KEYS if k not in attrs]
    return f"its attributes lack {missing}" if missing else None


def read_root(path: str | Path) -> dict:
    """Root attributes of a dataset; raises `DatasetError` for a missing or foreign folder."""
    path = Path(path)
    if not (path / "zarr.json").is_file():
        raise DatasetError(
            f"{path} is not a tt dataset: it has no zarr.json (create one with `tt generate --out {path}`)"
        )
    damage = root_damage(path)
    if damage is not None:
        raise DatasetError(
            f"{path / 'zarr.json'}, the dataset's root, is damaged ({damage}); re-running the `tt generate` "
            "command that wrote the dataset rebuilds it from its intact shards"
        )
    try:
        attrs = json.loads((path / "zarr.json").read_text()).get("attributes", {})
    except (UnicodeDecodeError, ValueError, AttributeError) as e:
        raise DatasetError(f"{path}/zarr.json is not valid JSON ({e}); the dataset root is damaged") from None
    if attrs.get("format") != FORMAT:
        raise DatasetError(f"{path} has format {attrs.get('format')!r}, this code reads {FORMAT!r}")
    check_version(attrs.get("schema_version", -1), f"dataset {path}")
    return attrs


def create_root(path: str | Path, attrs: Mapping) -> None:
    """Create the root group with `attrs` (plus format, schema and version); the folder must
    not hold a dataset yet."""
    import zarr

    path = Path(path)
    if (path / "zarr.json").exists():
        raise DatasetError(f"{path} already holds a zarr store")
    full = {
        "format": FORMAT,
        "schema_version": SCHEMA_VERSION,
        "schema": SCHEMA.to_dict(),
        "tt_version": tt_version(),
        **attrs,
    }
    zarr.create_group(str(path), zarr_format=3, attributes=_jsonable(full))
    (path / "shards").mkdir(exist_ok=True)


def update_root(path: str | Path, attrs: Mapping) -> None:
    """Merge `attrs` into the root attributes (zarr writes ``zarr.json`` atomically)."""
    import zarr

    g = zarr.open_group(str(path), mode="r+", zarr_format=3)
    g.attrs.update(_jsonable(dict(attrs)))


def _jsonable(x):
    """Numpy scalars and arrays -> Python numbers and lists (JSON attributes)."""
    if isinstance(x, Mapping):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    return x


# ------------------------------------------------------------------------------ shards on disk
def shard_dirs(path: str | Path) -> dict[int, Path]:
    """Shard folders present under ``shards/`` by index (complete or damaged; see `verify_shard`)."""
    root = Path(path) / "shards"
    out = {}
    if root.is_dir():
        for p in root.iterdir():
            m = _SHARD_RE.match(p.name)
            if m and p.is_dir():
                out[int(m.group(1))] = p
    return dict(sorted(out.items()))


def _crc32(path: Path) -> int:
    crc = 0
    with open(path, "rb") as f:
        while block := f.read(1 << 22):
            crc = zlib.crc32(block, crc)
    return crc


def _shard_files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file() and p.name != _MANIFEST)


def verify_shard(folder: str | Path, *, full: bool = True) -> str | None:
    """None if shard `folder` is complete and intact, else why not.

    Checks that ``manifest.json`` exists and parses and that every file it lists exists with
    its size; `full` also compares each file's CRC-32 (reads the whole shard).
    """
    folder = Path(folder)
    mpath = folder / _MANIFEST
    if not mpath.is_file():
        return "no manifest.json (the shard was never completed)"
    try:
        manifest = json.loads(mpath.read_text())
        files = manifest["files"]
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
        return f"manifest.json is damaged ({type(e).__name__}: {e})"
    if manifest.get("format") != FORMAT:
        return f"manifest.json has format {manifest.get('format')!r}, expected {FORMAT!r}"
    for rel, (size, crc) in sorted(files.items()):
        p = folder / rel
        if not p.is_file():
            return f"file {rel} is missing"
        actual = p.stat().st_size
        if actual != size:
            return f"file {rel} has {actual} bytes, the manifest says {size} (truncated or overwritten)"
        if full and _crc32(p) != crc:
            return f"file {rel} fails its CRC-32 check (content changed)"
    return None


def check_shards(path: str | Path, *, shards: int | None = None, full: bool = True) -> dict[int, str | None]:
    """Shard index -> None if the shard is intact, else why not (`verify_shard`), for every
    shard folder of dataset `path`; with `shards`, an index at or beyond it is damaged too.
    The check `tt generate` runs before it resumes, and `tt dataset verify`."""
    out = {}
    for i, folder in shard_dirs(path).items():
        out[i] = (
            verify_shard(folder, full=full) if shards is None or i < shards else f"index beyond the {shards} shards"
        )
    return out


def dataset_verify_cmd(path: str | Path) -> str:
    """``tt dataset verify DATASET``: sizes and CRC-32 of every file of every shard.

    Returns the summary; raises `DatasetError` (one line) naming each damaged shard and why.
    """
    path = Path(path)
    attrs = read_root(path)
    expected = attrs.get("config", {}).get("shards")
    verdicts = check_shards(path, shards=expected, full=True)
    damaged = {i: why for i, why in verdicts.items() if why is not None}
    if damaged:
        named = "; ".join(f"{shard_name(i)}: {why}" for i, why in list(damaged.items())[:5])
        more = f"; and {len(damaged) - 5} more" if len(damaged) > 5 else ""
        raise DatasetError(
            f"{path}: {len(damaged)} of {len(verdicts)} shards fail verification ({named}{more}); re-run "
            "the `tt generate` command that wrote the dataset to regenerate them"
        )
    missing = [] if expected is None else [i for i in range(expected) if i not in verdicts]
    files = sum(len(read_manifest(f)["files"]) for f in shard_dirs(path).values())
    text = f"{path}: all {len(verdicts)} shards intact ({files} files, sizes and CRC-32 checked)"
    if missing:
        text += f"; {len(missing)} of {expected} shards not generated yet (run `tt generate` again to finish)"
    return text


def dataset_fingerprint(path: str | Path) -> dict:
    """The identity of dataset `path`'s content, beyond its path: its generating config,
    its shard count and a digest of its shards' manifests (size and CRC-32 of every file;
    a shard is a pure function of the config and its index). A dataset regenerated at the
    same path with other arguments, or whose shards changed, has another fingerprint."""
    path = Path(path)
    attrs = read_root(path)
    h = hashlib.blake2b(digest_size=16)
    shards = shard_dirs(path)
    for _, folder in sorted(shards.items()):
        h.update(folder.name.encode())
        try:
            h.update((folder / _MANIFEST).read_bytes())
        except OSError:
            h.update(b"(no manifest)")
    return {
        "kind": "dataset",
        "config": _jsonable(attrs.get("config", {})),
        "shards": len(shards),
        "digest": h.hexdigest(),
    }


def read_manifest(folder: str | Path) -> dict:
    return json.loads((Path(folder) / _MANIFEST).read_text())


def discard_shard(path: str | Path, index: int) -> None:
    """Move a damaged shard out of ``shards/`` (into ``.partial/``) and delete it."""
    src = Path(path) / "shards" / shard_name(index)
    if not src.exists():
        return
    trash = Path(path) / ".partial" / f"discard-{shard_name(index)}-{uuid.uuid4().hex[:8]}"
    trash.parent.mkdir(exist_ok=True)
    os.rename(src, trash)
    shutil.rmtree(trash, ignore_errors=True)


def clear_partial(path: str | Path) -> int:
    """Delete leftovers of interrupted shard writes; returns how many were removed."""
    partial = Path(path) / ".partial"
    n = 0
    if partial.is_dir():
        for p in partial.iterdir():
            shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
            n += 1
    return n


# ------------------------------------------------------------------------------ writing
@dataclass
class ShardPart:
    """Tokens of some designs and their kept episodes, appended to a shard by `ShardWriter`.

    design_discrete: (D, nd) int option indices, -1 padded; design_continuous: (D, nc)
    float64, NaN padded. static[type] = (values (D, L, width) float32, ids (D, L, k),
    mask (D, L) bool), padded to the maxima. episode[field]: (E, ...) arrays; ``design``
    indexes this part's designs, ``length`` is each episode's number of steps (>= 1).
    steps[type] = (values (S, P, width) float32 with S = sum(length), the episodes' steps
    one after the other; ids (E, P, k); mask (E, P) bool), padded to the maxima.
    """

    design_discrete: np.ndarray
    design_continuous: np.ndarray
    static: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]
    episode: dict[str, np.ndarray]
    steps: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]

    def __post_init__(self) -> None:
        d = self.design_discrete.shape[0]
        if "design" not in self.episode or "length" not in self.episode:
            raise ValueError(f"ShardPart.episode needs 'design' and 'length'; got {sorted(self.episode)}")
        e = self.episode["design"].shape[0]
        for k, v in self.episode.items():
            if v.shape[0] != e:
                raise ValueError(f"episode[{k!r}] has {v.shape[0]} rows, episode['design'] has {e}")
        if e and (self.episode["design"].min() < 0 or self.episode["design"].max() >= d):
            raise ValueError(f"episode['design'] must index the part's {d} designs")
        s = int(self.episode["length"].sum())
        for name, (v, i, m) in self.static.items():
            if v.shape[0] != d or i.shape[:2] != v.shape[:2] or m.shape != v.shape[:2]:
                raise ValueError(f"static[{name!r}]: values {v.shape}, ids {i.shape}, mask {m.shape} for {d} designs")
        for name, (v, i, m) in self.steps.items():
            if v.shape[0] != s or i.shape[:2] != (e, v.shape[1]) or m.shape != (e, v.shape[1]):
                raise ValueError(
                    f"steps[{name!r}]: values {v.shape}, ids {i.shape}, mask {m.shape} for {e} episodes of {s} steps"
                )


class ShardWriter:
    """Writes one shard under ``.partial/`` and renames it into ``shards/`` on `commit`.

    Appended rows are buffered in memory up to `flush_bytes` before they reach zarr.

    ``with ShardWriter(...) as w: w.append(part); ...; w.commit(attrs)``; leaving the block
    without `commit` (an exception) deletes the partial shard.
    """

    def __init__(self, path: str | Path, index: int, *, flush_bytes: int = 256 << 20):
        import zarr

        self.path = Path(path)
        self.index = index
        self.name = shard_name(index)
        self.tmp = self.path / ".partial" / f"{self.name}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        self.tmp.parent.mkdir(parents=True, exist_ok=True)
        self.group = zarr.open_group(str(self.tmp), mode="w", zarr_format=3)
        self._arrays: dict[str, object] = {}
        self._pending: dict[str, list[np.ndarray]] = {}
        self._chunks: dict[str, int] = {}
        self._pending_bytes = 0
        self._length = (2**62, 0)
        self.flush_bytes = flush_bytes
        self.designs = 0
        self.episodes = 0
        self.steps = 0
        self._lo: dict[str, np.ndarray] = {}
        self._hi: dict[str, np.ndarray] = {}
        self.committed = False

    def __enter__(self) -> "ShardWriter":
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if not self.committed:
            shutil.rmtree(self.tmp, ignore_errors=True)

    def _append(self, key: str, data: np.ndarray, chunk: int) -> None:
        # Buffered: every zarr call costs milliseconds, so arrays are written in few large appends.
        if key in self._pending:
            first = self._pending[key][0]
            if first.shape[1:] != data.shape[1:] or first.dtype != data.dtype:
                raise ValueError(
                    f"{self.name}/{key}: appending {data.dtype}{data.shape[1:]} to an array of "
                    f"{first.dtype}{first.shape[1:]}"
                )
        else:
            self._chunks[key] = chunk
        self._pending.setdefault(key, []).append(data)
        self._pending_bytes += data.nbytes

    def flush(self) -> None:
        """Write the buffered rows of every array."""
        for key, parts in self._pending.items():
            data = np.concatenate(parts) if len(parts) > 1 else parts[0]
            arr = self._arrays.get(key)
            if arr is None:
                fill = np.nan if data.dtype.kind == "f" and key.endswith("continuous") else 0
                self._arrays[key] = self.group.create_array(
                    key,
                    data=data,
                    chunks=(self._chunks[key], *data.shape[1:]),
                    compressors=_compressor(),
                    fill_value=fill,
                )
            elif data.shape[0]:
                arr.append(data, axis=0)
            self._pending[key] = [data[:0]]
        self._pending_bytes = 0

    def _stats(self, name: str, values: np.ndarray, real: np.ndarray) -> None:
        if not real.any():
            return
        axes = tuple(range(real.ndim))
        where = np.broadcast_to(real[..., None], values.shape)  # reduce in place, no copy of the real tokens
        lo = values.min(axis=axes, initial=np.inf, where=where).astype(np.float64)
        hi = values.max(axis=axes, initial=-np.inf, where=where).astype(np.float64)
        self._lo[name] = np.minimum(self._lo[name], lo) if name in self._lo else lo
        self._hi[name] = np.maximum(self._hi[name], hi) if name in self._hi else hi

    def append(self, part: ShardPart) -> None:
        """Append designs, their static tokens and their episodes' per-step tokens."""
        self._append("design/discrete", part.design_discrete.astype(np.int16), DESIGN_CHUNK)
        self._append("design/continuous", part.design_continuous.astype(np.float64), DESIGN_CHUNK)
        for name, (v, i, m) in part.static.items():
            self._append(f"{name}/values", v.astype(np.float32), DESIGN_CHUNK)
            self._append(f"{name}/ids", i.astype(np.int32), DESIGN_CHUNK)
            self._append(f"{name}/mask", m.astype(bool), DESIGN_CHUNK)
            self._stats(name, v, m)
        length = part.episode["length"].astype(np.int64)
        starts = self.steps + np.concatenate([[0], np.cumsum(length)[:-1]]).astype(np.int64) if len(length) else length
        fields = dict(part.episode)
        fields["design"] = part.episode["design"].astype(np.int32) + self.designs
        fields["step_start"] = starts
        fields["length"] = length.astype(np.int32)
        for k in sorted(fields):
            self._append(f"episode/{k}", np.ascontiguousarray(fields[k]), EPISODE_CHUNK)
        row_episode = np.repeat(np.arange(len(length)), length)
        for name, (v, i, m) in part.steps.items():
            self._append(f"{name}/values", v.astype(np.float32), STEP_CHUNK)
            self._append(f"{name}/ids", i.astype(np.int32), EPISODE_CHUNK)
            self._append(f"{name}/mask", m.astype(bool), EPISODE_CHUNK)
            self._stats(name, v, m[row_episode])
        self.designs += part.design_discrete.shape[0]
        self.episodes += len(length)
        self.steps += int(length.sum())
        if len(length):
            self._length = (min(self._length[0], int(length.min())), max(self._length[1], int(length.max())))
        if self._pending_bytes >= self.flush_bytes:
            self.flush()

    def commit(self, attrs: Mapping, *, fsync: bool = True) -> Path:
        """Finish the shard: attributes, manifest (sizes and CRC-32 of every file), fsync, rename.

        attrs: stored in the shard group's ``zarr.json`` (content: part of the checksums).
        Nothing that differs between runs (timings) is stored, so a shard is a pure function
        of its arguments and index, manifest included. An existing damaged shard of the same
        index is replaced; an intact one is kept (another writer finished it first) and this
        one discarded.
        """
        self.flush()
        stats = {name: {"min": self._lo[name].tolist(), "max": self._hi[name].tolist()} for name in self._lo}
        self.group.attrs.update(
            _jsonable(
                {
                    **attrs,
                    "index": self.index,
                    "designs": self.designs,
                    "episodes": self.episodes,
                    "steps": self.steps,
                    "stats": stats,
                    "length_min": self._length[0] if self.episodes else 0,
                    "length_max": self._length[1],
                }
            )
        )
        files = {}
        for rel in _shard_files(self.tmp):
            p = self.tmp / rel
            if fsync:
                with open(p, "rb+") as f:
                    os.fsync(f.fileno())
            files[rel] = [p.stat().st_size, _crc32(p)]
        manifest = {"format": FORMAT, "index": self.index, "files": files}
        mpath = self.tmp / _MANIFEST
        mpath.write_text(json.dumps(manifest))
        if fsync:
            with open(mpath, "rb+") as f:
                os.fsync(f.fileno())
        final = self.path / "shards" / self.name
        final.parent.mkdir(exist_ok=True)
        if final.exists():
            if verify_shard(final, full=False) is None:
                logger.warning("shard %s was completed by another writer; keeping that one", self.name)
                shutil.rmtree(self.tmp, ignore_errors=True)
                self.committed = True
                return final
            discard_shard(self.path, self.index)
        os.rename(self.tmp, final)
        if fsync:
            fd = os.open(final.parent, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        self.committed = True
        return final


# ------------------------------------------------------------------------------ statistics
def merge_stats(stats: Iterable[Mapping]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per-type (min, max) over several shards' ``stats`` attributes."""
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for s in stats:
        for name, mm in s.items():
            lo, hi = np.asarray(mm["min"], np.float64), np.asarray(mm["max"], np.float64)
            if name in out:
                lo, hi = np.minimum(out[name][0], lo), np.maximum(out[name][1], hi)
            out[name] = (lo, hi)
    return out


def normalizer_from_stats(stats: Mapping[str, tuple[np.ndarray, np.ndarray]]):
    """`tt.tokens.normalize.Normalizer` of data whose per-value minima and maxima are `stats`.

    Fits on a two-sample batch (the minima and the maxima), which gives exactly the ranges a
    fit over all the data gives (fixed ranges of bits and rotations, minimum widths)."""
    from tt.tokens.batch import TokenBatch
    from tt.tokens.normalize import Normalizer

    values, ids, mask = {}, {}, {}
    for name, (lo, hi) in stats.items():
        values[name] = np.stack([lo, hi])[:, None, :]
        ids[name] = np.zeros((2, 1, len(SCHEMA[name].ids)), np.int64)
        mask[name] = np.ones((2, 1), bool)
    return Normalizer.fit(TokenBatch(values, ids, mask))


# ------------------------------------------------------------------------------ reading
@dataclass
class EpisodeBlock:
    """Tokens of consecutive episodes of one shard, in memory (numpy).

    length: (n,) steps per episode; design: (n,) row of each episode's robot in ``static``;
    static[type] = (values (D, L, width), ids (D, L, k), mask (D, L)) of the block's designs;
    steps[type] = (values (S, P, width) of the block's steps, ids (n, P, k), mask (n, P));
    offset: (n,) first row of each episode in the step values; episode: per-episode fields
    (empty unless read with ``fields=True``).
    """

    length: np.ndarray
    design: np.ndarray
    offset: np.ndarray
    static: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]
    steps: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]
    episode: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.length.shape[0])

    def windows(self, episodes: np.ndarray, step_index: np.ndarray) -> dict[str, dict[str, np.ndarray]]:
        """Raw tokens of windows, laid out as `tt.dit.layout` expects.

        episodes: (B,) episodes of this block; step_index: (B, K) steps of each (each below
        its episode's length). Returns {"values", "ids", "mask"} -> type -> arrays:
        embodiment types (B, L, ...), per-step types (B, K * P, ...) time-major, time IDs =
        step indices.
        """
        episodes = np.asarray(episodes, np.int64)
        step_index = np.asarray(step_index, np.int64)
        if step_index.shape[0] != episodes.shape[0]:
            raise ValueError(f"step_index has {step_index.shape[0]} rows for {episodes.shape[0]} episodes")
        if len(episodes) and (step_index >= self.length[episodes][:, None]).any():
            raise ValueError("step_index holds steps past an episode's length")
        b, k = step_index.shape
        values, ids, mask = {}, {}, {}
        d = self.design[episodes]
        for name, (v, i, m) in self.static.items():
            values[name], ids[name], mask[name] = v[d], i[d].astype(np.int64), m[d]
        rows = self.offset[episodes][:, None] + step_index  # (B, K)
        for name, (v, i, m) in self.steps.items():
            p = v.shape[1]
            values[name] = v[rows].reshape(b, k * p, v.shape[2])
            t = SCHEMA[name].ids.index("time")
            ii = np.repeat(i[episodes][:, None].astype(np.int64), k, axis=1)  # (B, K, P, nid)
            ii[..., t] = step_index[:, :, None]
            ids[name] = ii.reshape(b, k * p, -1)
            mask[name] = np.repeat(m[episodes][:, None], k, axis=1).reshape(b, k * p)
        return {"values": values, "ids": ids, "mask": mask}


class ShardReader:
    """Reads one complete shard: index arrays on first use, blocks of episodes on demand."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self._arrays: dict[str, object] = {}
        self._fields: dict[str, np.ndarray] = {}

    def _damaged(self, what: str, error: BaseException) -> DatasetError:
        dataset = self.folder.parent.parent
        return DatasetError(
            f"dataset shard {self.folder}: {what} cannot be read ({reason(error)}); "
            f"`tt dataset verify {dataset}` checks every chunk, and re-running the `tt generate` "
            "command that wrote it regenerates a damaged shard"
        )

    def _read(self, key: str, rows: slice = slice(None)) -> np.ndarray:
        """Rows `rows` of array `key` of the shard; a chunk that does not decode is a `DatasetError`."""
        import zarr

        try:
            if key not in self._arrays:
                self._arrays[key] = zarr.open_array(str(self.folder / key), mode="r", zarr_format=3)
            return np.asarray(self._arrays[key][rows])
        except Exception as e:  # blosc, zarr and json raise unrelated types for a damaged chunk or header
            raise self._damaged(f"array {key}", e) from None

    @cached_property
    def attrs(self) -> dict:
        try:
            return json.loads((self.folder / "zarr.json").read_text())["attributes"]
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise self._damaged("zarr.json", e) from None

    def field(self, name: str) -> np.ndarray:
        """Per-episode field `name` of every episode (read once, then kept)."""
        if name not in self._fields:
            self._fields[name] = self._read(f"episode/{name}")
        return self._fields[name]

    @property
    def index(self) -> dict[str, np.ndarray]:
        """Every per-episode field of every episode (small: a few numbers per episode)."""
        keys = sorted(p.name for p in (self.folder / "episode").iterdir() if (p / "zarr.json").is_file())
        return {k: self.field(k) for k in keys}

    @property
    def episodes(self) -> int:
        return int(self.attrs["episodes"])

    @cached_property
    def types(self) -> tuple[str, ...]:
        return tuple(n for n in SCHEMA.names() if (self.folder / n / "zarr.json").is_file())

    def static_rows(self, start: int, stop: int) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Embodiment tokens (values, ids, mask) of designs [start, stop) of the shard."""
        return {
            n: tuple(self._read(f"{n}/{part}", slice(start, stop)) for part in ("values", "ids", "mask"))
            for n in self.types
            if n in EMBODIMENT_TYPES
        }

    @property
    def static(self) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Embodiment tokens of every design of the shard."""
        return self.static_rows(0, int(self.attrs["designs"]))

    def read_block(self, start: int, stop: int, *, fields: bool = False) -> EpisodeBlock:
        """Episodes [start, stop) of the shard: one contiguous read per array (the block's
        steps, its episodes' entity IDs and masks, its robots' tokens). fields: also return
        every per-episode field (``EpisodeBlock.episode``)."""
        if not 0 <= start < stop <= self.episodes:
            raise ValueError(f"block [{start}, {stop}) is outside the shard's {self.episodes} episodes")
        length = self.field("length")[start:stop].astype(np.int64)
        step_start = self.field("step_start")[start:stop].astype(np.int64)
        design = self.field("design")[start:stop].astype(np.int64)
        s0, s1 = int(step_start[0]), int(step_start[-1] + length[-1])
        d0, d1 = int(design.min()), int(design.max()) + 1
        steps = {}
        for n in self.types:
            if n in EMBODIMENT_TYPES:
                continue
            steps[n] = (
                self._read(f"{n}/values", slice(s0, s1)),
                self._read(f"{n}/ids", slice(start, stop)),
                self._read(f"{n}/mask", slice(start, stop)),
            )
        episode = {k: v[start:stop] for k, v in self.index.items()} if fields else {}
        return EpisodeBlock(
            length=length,
            design=design - d0,
            offset=step_start - s0,
            static=self.static_rows(d0, d1),
            steps=steps,
            episode=episode,
        )

    def designs(self, space) -> list:
        """The shard's designs as `tt.sim.designs.Design` of `space` (a DesignSpace)."""
        from tt.sim.designs import Design

        disc = self._read("design/discrete")
        cont = self._read("design/continuous")
        out = []
        for d, c in zip(disc, cont):
            out.append(
                Design(space.name, tuple(int(v) for v in d if v >= 0), tuple(float(v) for v in c if not np.isnan(v)))
            )
        return out

    def episode_digests(self) -> dict[int, str]:
        """episode_id -> BLAKE2b digest of everything stored about the episode (its fields,
        its robot's tokens and every step's tokens); equal digests mean equal data."""
        out = {}
        n = self.episodes
        for start in range(0, n, BLOCK_EPISODES):
            block = self.read_block(start, min(n, start + BLOCK_EPISODES), fields=True)
            for e in range(len(block)):
                h = hashlib.blake2b(digest_size=16)
                for k in sorted(block.episode):
                    if k not in ("design", "step_start"):  # positions in the shard, not content
                        h.update(k.encode() + np.ascontiguousarray(block.episode[k][e]).tobytes())
                for name in sorted(block.static):
                    for a in block.static[name]:
                        h.update(np.ascontiguousarray(a[block.design[e]]).tobytes())
                o, ln = block.offset[e], block.length[e]
                for name in sorted(block.steps):
                    v, i, m = block.steps[name]
                    h.update(
                        name.encode() + np.ascontiguousarray(v[o : o + ln]).tobytes() + i[e].tobytes() + m[e].tobytes()
                    )
                out[int(block.episode["episode_id"][e])] = h.hexdigest()
        return out


class TokenStore:
    """A dataset folder opened for reading: its root attributes and its complete shards.

    verify: "size" checks each shard's files against its manifest by size (cheap),
    "full" also by CRC-32, "none" trusts the manifests. Damaged shards are skipped with a
    warning (`tt generate` on the same folder regenerates them).
    """

    def __init__(self, path: str | Path, *, verify: str = "size", require_complete: bool = False):
        if verify not in ("none", "size", "full"):
            raise TTError(f"verify must be 'none', 'size' or 'full', got {verify!r}")
        self.path = Path(path)
        self.attrs = read_root(self.path)
        if require_complete and not self.attrs.get("complete"):
            raise DatasetError(
                f"{self.path} is incomplete (its generation was interrupted); run the same "
                "`tt generate` command again to finish it"
            )
        self.readers: list[ShardReader] = []
        self.damaged: dict[int, str] = {}
        for index, folder in shard_dirs(self.path).items():
            why = None if verify == "none" else verify_shard(folder, full=verify == "full")
            if why is not None:
                logger.warning(
                    "skipping damaged shard %s of %s: %s (re-running the `tt generate` command that wrote it "
                    "regenerates it)",
                    folder.name,
                    self.path,
                    why,
                )
                self.damaged[index] = why
                continue
            self.readers.append(ShardReader(folder))
        counts = np.array([r.episodes for r in self.readers], np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)

    @property
    def episodes(self) -> int:
        return int(self.offsets[-1])

    @property
    def space(self) -> str:
        return str(self.attrs["space"])

    @property
    def maxima(self) -> dict[str, int]:
        """Tokens per robot (embodiment types) or per step (per-step types) of the space's largest robot."""
        return {k: int(v) for k, v in self.attrs["maxima"].items() if int(v) > 0}

    def normalizer(self):
        """`tt.tokens.normalize.Normalizer` of the whole dataset (stored, else merged from the shards)."""
        from tt.tokens.normalize import Normalizer

        if "normalizer" in self.attrs:
            return Normalizer.from_dict(self.attrs["normalizer"])
        return normalizer_from_stats(merge_stats(r.attrs["stats"] for r in self.readers))

    def blocks(self, episodes_per_block: int = BLOCK_EPISODES) -> list[tuple[int, int, int]]:
        """(shard position, start, stop) of every block of episodes."""
        out = []
        for s, r in enumerate(self.readers):
            out += [(s, a, min(r.episodes, a + episodes_per_block)) for a in range(0, r.episodes, episodes_per_block)]
        return out

    def locate(self, episode: int) -> tuple[int, int]:
        """(shard position, episode within the shard) of global episode `episode`."""
        if not 0 <= episode < self.episodes:
            raise IndexError(f"episode {episode} is out of range: the dataset holds {self.episodes}")
        s = int(np.searchsorted(self.offsets, episode, side="right") - 1)
        return s, int(episode - self.offsets[s])

    def episode_table(self) -> dict[str, np.ndarray]:
        """Per-episode fields of every episode, concatenated over shards."""
        keys = set.intersection(*(set(r.index) for r in self.readers)) if self.readers else set()
        return {k: np.concatenate([r.index[k] for r in self.readers]) for k in sorted(keys)}

    def episode_digests(self) -> dict[int, str]:
        out = {}
        for r in self.readers:
            out.update(r.episode_digests())
        return out


__all__ = [
    "BLOCK_EPISODES",
    "DatasetError",
    "EpisodeBlock",
    "FORMAT",
    "ShardPart",
    "ShardReader",
    "ShardWriter",
    "TokenStore",
    "check_shards",
    "clear_partial",
    "create_root",
    "dataset_fingerprint",
    "dataset_verify_cmd",
    "discard_shard",
    "is_dataset",
    "merge_stats",
    "normalizer_from_stats",
    "read_manifest",
    "read_root",
    "shard_dirs",
    "shard_name",
    "update_root",
    "verify_shard",
]
