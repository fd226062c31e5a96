"""Training windows from a RoboToken dataset (`tt.tokens.store`): a streaming torch
`IterableDataset` / `DataLoader`, and a `tt.dit.data.TokenSource` for ``tt train``.

A window is 8 control steps of one episode (paper): distinct steps drawn uniformly and put
in time order ("random", motion-to-robot) or a run of consecutive steps at a uniform start
("consecutive", control). Its tokens: the robot's embodiment tokens and the per-step tokens
of the chosen steps (time-major, time ID = step index), every type padded to the design
space's maximum (`TokenStore.maxima`), masks True for real tokens. Values are raw
(unnormalised); the DiT's normaliser maps them and sets padding to -1.

Planar SE(2) augmentation (`SE2Augment`): gravity fixes z, so rotating the whole scene
(robot and targets) about the vertical and shifting it in the plane gives another valid
episode. On tokens: world poses (track-link and free-link observations, target poses)
become ``g * pose``; a joint token that holds the ground's pose in its joint frame (link
ID -1: the robot's mount) becomes ``pose * g^-1``; everything else is in body frames and
does not change.

Reading streams blocks of consecutive episodes (`tt.tokens.store.BLOCK_EPISODES`): a block
is one contiguous read per array, and every window of a batch comes from a few blocks, so
the store is never loaded whole.
"""

from __future__ import annotations

import hashlib
import logging
import math
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
import torch

from tt.kernels.errors import TTError
from tt.tokens.schema import SCHEMA
from tt.tokens.store import BLOCK_EPISODES, DatasetError, EpisodeBlock, TokenStore, is_dataset

logger = logging.getLogger(__name__)

WINDOW_KINDS = ("random", "start", "consecutive")
#: Types holding world poses, transformed as g * pose.
_WORLD_POSE_TYPES = ("free_link_obs", "track_link_obs", "target_pose")
#: Joint types whose token may hold the ground's pose in the joint frame (link ID -1).
_JOINT_TYPES = ("dyna_joint", "ball_joint", "fixed_joint")


@dataclass(frozen=True)
class SE2Augment:
    """Planar augmentation drawn per window: yaw ~ U(-max_yaw, max_yaw) [rad] about the world
    z axis, then a shift with dx, dy ~ U(-max_shift, max_shift) [m]. The defaults match the
    motion augmentation of data generation (`tt.sim.motions.augment_motion`)."""

    max_yaw: float = math.pi / 8
    max_shift: float = 0.03

    def __post_init__(self) -> None:
        if not (0 <= self.max_yaw <= math.pi and self.max_shift >= 0):
            raise TTError(
                f"SE2Augment needs 0 <= max_yaw <= pi and max_shift >= 0, got {self.max_yaw}, {self.max_shift}"
            )

    def draw(self, n: int, generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """yaw, dx, dy of n windows, each (n,) float64."""
        u = torch.rand(n, 3, generator=generator, dtype=torch.float64) * 2 - 1
        return u[:, 0] * self.max_yaw, u[:, 1] * self.max_shift, u[:, 2] * self.max_shift


def augment_se2_tokens(
    values: dict[str, torch.Tensor],
    mask: dict[str, torch.Tensor],
    yaw: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
) -> dict[str, torch.Tensor]:
    """Raw tokens of B windows under the planar transforms g = (yaw, dx, dy), each (B,).

    values[type]: (B, L, width) raw (encoded, unnormalised) tokens; mask[type]: (B, L).
    Returns new value tensors (types without world quantities are passed through).
    """
    b = yaw.shape[0]
    c, s = torch.cos(yaw), torch.sin(yaw)
    zero, one = torch.zeros_like(yaw), torch.ones_like(yaw)
    rot = torch.stack([c, -s, zero, s, c, zero, zero, zero, one], -1).reshape(b, 1, 3, 3)  # (B, 1, 3, 3)
    shift = torch.stack([dx, dy, zero], -1).reshape(b, 1, 3)
    out = dict(values)
    for name in _WORLD_POSE_TYPES:
        if name not in values:
            continue
        t = SCHEMA[name]
        v = values[name]
        x = v.double()
        pos, r = x[..., t.slice("pos")], x[..., t.slice("rot")].reshape(*x.shape[:2], 3, 3)
        new = x.clone()
        new[..., t.slice("pos")] = (rot @ pos[..., None])[..., 0] + shift
        new[..., t.slice("rot")] = (rot @ r).reshape(*x.shape[:2], 9)
        out[name] = torch.where(mask[name][..., None], new.to(v.dtype), v)
    for name in _JOINT_TYPES:
        if name not in values:
            continue
        t = SCHEMA[name]
        v = values[name]
        x = v.double()
        ground = (x[..., t.slice("link_id")] < 0.5).all(-1) & mask[name]  # link ID -1 encodes as all-zero bits
        pos, r = x[..., t.slice("pos")], x[..., t.slice("rot")].reshape(*x.shape[:2], 3, 3)
        r_new = r @ rot.transpose(-1, -2)  # T * g^-1: R R_g^T, p - R R_g^T t
        new = x.clone()
        new[..., t.slice("rot")] = r_new.reshape(*x.shape[:2], 9)
        new[..., t.slice("pos")] = pos - (r_new @ shift[..., None])[..., 0]
        out[name] = torch.where(ground[..., None], new.to(v.dtype), v)
    return out


def window_steps(
    lengths: torch.Tensor, steps: int, kind: str, generator: torch.Generator | None = None
) -> torch.Tensor:
    """Step indices (n, steps), ascending, of windows of episodes with `lengths` (n,).

    "random": `steps` distinct steps uniform among the episode's, sorted; "start": step 0 and
    `steps` - 1 distinct others uniform among the rest, sorted; "consecutive":
    steps start .. start + steps - 1 with a uniform start. Same draws as
    `tt.dit.data.EpisodeTokens.window_steps`."""
    if kind not in WINDOW_KINDS:
        raise TTError(f"window kind {kind!r} does not exist; kinds: {list(WINDOW_KINDS)}")
    if len(lengths) and int(lengths.min()) < steps:
        raise TTError(f"an episode has {int(lengths.min())} steps, fewer than the window's {steps}")
    n = lengths.shape[0]
    if kind in ("random", "start"):
        width = int(lengths.max()) if n else steps
        scores = torch.rand(n, width, generator=generator)
        scores = torch.where(torch.arange(width)[None, :] < lengths[:, None], scores, torch.full_like(scores, 2.0))
        if kind == "start":
            scores[:, 0] = -1.0
        return scores.topk(steps, dim=1, largest=False).indices.sort(dim=1).values
    start = (torch.rand(n, generator=generator) * (lengths - steps + 1)).long()
    return start[:, None] + torch.arange(steps)[None, :]


def _tensors(parts: list[dict]):
    """Numpy window dicts (`EpisodeBlock.windows`) -> one `tt.tokens.batch.TokenBatch`."""
    from tt.tokens.batch import TokenBatch

    names = list(parts[0]["values"])
    cat = lambda key, name, dt: torch.from_numpy(np.concatenate([p[key][name] for p in parts])).to(dt)  # noqa: E731
    return TokenBatch(
        {n: cat("values", n, torch.float32) for n in names},
        {n: cat("ids", n, torch.int64) for n in names},
        {n: cat("mask", n, torch.bool) for n in names},
    )


class _BlockCache:
    """Least-recently-used blocks, bounded in bytes; only a speed-up (contents never change)."""

    def __init__(self, store: TokenStore, max_bytes: int):
        self.store = store
        self.max_bytes = max_bytes
        self.blocks: OrderedDict[tuple[int, int, int], tuple[EpisodeBlock, int]] = OrderedDict()
        self.bytes = 0

    def get(self, key: tuple[int, int, int]) -> EpisodeBlock:
        if key in self.blocks:
            self.blocks.move_to_end(key)
            return self.blocks[key][0]
        s, a, b = key
        block = self.store.readers[s].read_block(a, b)
        size = sum(v[0].nbytes for v in block.steps.values())
        if size <= self.max_bytes:
            self.blocks[key] = (block, size)
            self.bytes += size
            while self.bytes > self.max_bytes:
                _, (_, n) = self.blocks.popitem(last=False)
                self.bytes -= n
        return block


class StoreTokenSource:
    """A dataset folder as ``tt train`` training data (`tt.dit.data.TokenSource`).

    ``sample(n, steps, kind, generator)`` draws every random number from `generator`, so a
    resumed training run sees the same windows: it picks ceil(n / windows_per_block) blocks
    with probability proportional to their episode counts, then n episodes uniformly within
    them (every episode equally likely), then steps and the SE(2) transform.

    path: dataset folder; augment: planar augmentation (None: off); windows_per_block:
    windows drawn from one block (higher: fewer reads, more correlated batches);
    cache_bytes: memory for recently read blocks; max_time: time-ID rows of the layout.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        augment: SE2Augment | None = SE2Augment(),
        windows_per_block: int = 16,
        block_episodes: int = BLOCK_EPISODES,
        cache_bytes: int = 1 << 30,
        max_time: int = 1024,
        verify: str = "size",
    ):
        self.store = TokenStore(path, verify=verify)
        if self.store.episodes == 0 and self.store.damaged:
            raise DatasetError(
                f"dataset {path}: every shard with episodes fails verification "
                f"({'; '.join(f'shard {i}: {w}' for i, w in sorted(self.store.damaged.items())[:3])}); "
                "re-run the `tt generate` command that wrote it to regenerate them"
            )
        if self.store.episodes == 0 and self.store.attrs.get("complete"):
            totals = self.store.attrs.get("totals") or {}
            dropped = ", ".join(f"{v:,} {k}" for k, v in sorted((totals.get("dropped") or {}).items()) if v)
            min_steps = (self.store.attrs.get("config") or {}).get("min_steps")
            raise DatasetError(
                f"dataset {path} is complete but holds no episodes: all {totals.get('generated', '?')} "
                f"generated episodes were dropped ({dropped or 'every one'}; it was generated with "
                f"min_steps={min_steps}); generate it again into another --out with a lower min_steps"
            )
        if self.store.episodes == 0:
            raise TTError(f"dataset {path} holds no episodes yet; run its `tt generate` command to generate them")
        if not self.store.attrs.get("complete"):
            logger.warning("dataset %s is incomplete; training on its %d episodes so far", path, self.store.episodes)
        if windows_per_block < 1:
            raise TTError(f"windows_per_block must be >= 1, got {windows_per_block}")
        self.augment = augment
        self.windows_per_block = windows_per_block
        self.max_time = max_time
        self.blocks = self.store.blocks(block_episodes)
        self.block_sizes = torch.tensor([b - a for _, a, b in self.blocks], dtype=torch.float64)
        self._cache = _BlockCache(self.store, cache_bytes)
        lengths = [(r.attrs["length_min"], r.attrs["length_max"]) for r in self.store.readers if r.episodes]
        self.shortest, self.longest = min(a for a, _ in lengths), max(b for _, b in lengths)

    def __len__(self) -> int:
        return self.store.episodes

    @property
    def design_space(self) -> str | None:
        """Name of the design space the dataset was generated from (recorded in checkpoints)."""
        return self.store.attrs.get("space")

    def layout(self, steps: int = 8):
        """`tt.dit.layout.Layout` of the design space's largest robot, windows of `steps` steps."""
        from tt.dit.layout import LayoutError, layout_from_schema

        layout = layout_from_schema(self.store.maxima, steps=steps, max_time=self.max_time)
        if self.longest > self.max_time:
            raise LayoutError(f"episodes have up to {self.longest} steps but time IDs only {self.max_time} rows")
        return layout

    def fit_normalizer(self):
        """`tt.tokens.normalize.Normalizer` from the dataset's stored statistics."""
        return self.store.normalizer()

    def sample(
        self,
        n: int,
        steps: int,
        kind: str,
        generator: torch.Generator | None = None,
        part: tuple[int, int] | None = None,
    ):
        """n raw windows (`tt.tokens.batch.TokenBatch`), drawn with `generator` (CPU).
        part: (a, b): only windows a .. b - 1 of the n (a data-parallel rank's share): the
        random numbers drawn are those of all n, and only those windows are built."""
        if steps > self.shortest:
            raise TTError(
                f"windows of {steps} steps need episodes of >= {steps} steps; the shortest has {self.shortest}"
            )
        lo, hi = (0, n) if part is None else part
        g = max(1, -(-n // self.windows_per_block))
        chosen = torch.multinomial(self.block_sizes, g, replacement=True, generator=generator)
        which = torch.arange(n) % g
        parts, first = [], 0  # first: index of the block's first window in the output order
        for j in range(g):
            k = int((which == j).sum())
            if k == 0:
                continue
            # The step draws depend on the drawn episodes' lengths, so every block of the
            # batch is opened (the block cache keeps them); only the part's windows are built.
            block = self._cache.get(self.blocks[int(chosen[j])])
            ep = torch.randint(0, len(block), (k,), generator=generator)
            st = window_steps(torch.from_numpy(block.length)[ep], steps, kind, generator)
            a, b = max(lo - first, 0), min(hi - first, k)  # this block's windows in the part
            if a < b:
                parts.append(block.windows(ep[a:b].numpy(), st[a:b].numpy()))
            first += k
        out = _tensors(parts)
        if self.augment is not None:
            yaw, dx, dy = self.augment.draw(n, generator)
            out.values = augment_se2_tokens(out.values, out.mask, yaw[lo:hi], dx[lo:hi], dy[lo:hi])
        return out


class EpisodeWindows(torch.utils.data.IterableDataset):
    """Batches of windows streamed from a dataset folder, for a `torch.utils.data.DataLoader`
    with ``batch_size=None`` (see `make_loader`).

    Each epoch shuffles the blocks (seeded by seed and epoch), gives DataLoader worker w the
    blocks w, w + workers, ...; reads `shuffle_blocks` of them at a time, and yields their
    episodes' windows (`windows_per_episode` each) in random order in batches of `batch_size`
    `tt.tokens.batch.TokenBatch` (values (B, L, width), ids (B, L, k), mask (B, L)).
    epochs: None streams forever. drop_last: drop each worker's last, smaller batch.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        batch_size: int = 64,
        steps: int = 8,
        kind: str = "random",
        augment: SE2Augment | None = SE2Augment(),
        seed: int = 0,
        epochs: int | None = 1,
        windows_per_episode: int = 1,
        shuffle_blocks: int = 8,
        block_episodes: int = BLOCK_EPISODES,
        drop_last: bool = False,
    ):
        super().__init__()
        if kind not in WINDOW_KINDS:
            raise TTError(f"window kind {kind!r} does not exist; kinds: {list(WINDOW_KINDS)}")
        for name in ("batch_size", "steps", "windows_per_episode", "shuffle_blocks", "block_episodes"):
            if locals()[name] < 1:
                raise TTError(f"{name} must be >= 1, got {locals()[name]}")
        self.path = str(path)
        self.batch_size, self.steps, self.kind = batch_size, steps, kind
        self.augment, self.seed, self.epochs = augment, seed, epochs
        self.windows_per_episode, self.shuffle_blocks = windows_per_episode, shuffle_blocks
        self.block_episodes, self.drop_last = block_episodes, drop_last
        self._store: TokenStore | None = None

    @property
    def store(self) -> TokenStore:
        # Opened lazily, so each DataLoader worker process opens its own.
        if self._store is None:
            self._store = TokenStore(self.path, verify="none")
        return self._store

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_store": None}

    def __iter__(self) -> Iterator:
        info = torch.utils.data.get_worker_info()
        wid, workers = (0, 1) if info is None else (info.id, info.num_workers)
        blocks = self.store.blocks(self.block_episodes)
        epoch = 0
        while self.epochs is None or epoch < self.epochs:
            order = np.random.default_rng([self.seed, epoch]).permutation(len(blocks))[wid::workers]
            gen = torch.Generator().manual_seed(
                int(np.random.SeedSequence([self.seed, epoch, wid]).generate_state(1)[0])
            )
            carry: list[tuple[EpisodeBlock, int]] = []
            for g0 in range(0, len(order), self.shuffle_blocks):
                loaded = [
                    self.store.readers[blocks[i][0]].read_block(*blocks[i][1:])
                    for i in order[g0 : g0 + self.shuffle_blocks]
                ]
                items = carry + [
                    (blk, e) for blk in loaded for e in range(len(blk)) for _ in range(self.windows_per_episode)
                ]
                perm = torch.randperm(len(items), generator=gen).tolist()
                items = [items[i] for i in perm]
                full = len(items) - len(items) % self.batch_size
                for b0 in range(0, full, self.batch_size):
                    yield self._batch(items[b0 : b0 + self.batch_size], gen)
                carry = items[full:]
            if carry and not self.drop_last:
                yield self._batch(carry, gen)
            epoch += 1

    def _batch(self, items: list[tuple[EpisodeBlock, int]], gen: torch.Generator):
        parts = []
        by_block: dict[int, tuple[EpisodeBlock, list[int]]] = {}
        for blk, e in items:
            by_block.setdefault(id(blk), (blk, []))[1].append(e)
        for blk, eps in by_block.values():
            ep = np.asarray(eps, np.int64)
            st = window_steps(torch.from_numpy(blk.length[ep]), self.steps, self.kind, gen)
            parts.append(blk.windows(ep, st.numpy()))
        out = _tensors(parts)
        if self.augment is not None:
            yaw, dx, dy = self.augment.draw(len(items), gen)
            out.values = augment_se2_tokens(out.values, out.mask, yaw, dx, dy)
        return out


def _identity(batch):
    return batch


def make_loader(
    path: str | Path,
    *,
    batch_size: int = 64,
    steps: int = 8,
    kind: str = "random",
    workers: int = 0,
    seed: int = 0,
    epochs: int | None = 1,
    augment: SE2Augment | None = SE2Augment(),
    **kwargs,
) -> torch.utils.data.DataLoader:
    """A DataLoader of `EpisodeWindows` batches (`tt.tokens.batch.TokenBatch`); `workers`
    processes read in parallel. Extra keyword arguments go to `EpisodeWindows`."""
    ds = EpisodeWindows(
        path, batch_size=batch_size, steps=steps, kind=kind, augment=augment, seed=seed, epochs=epochs, **kwargs
    )
    return torch.utils.data.DataLoader(
        ds,
        batch_size=None,
        num_workers=workers,
        collate_fn=_identity,
        persistent_workers=workers > 0 and epochs is None,
    )


def data_identity(path: str | Path) -> dict:
    """What training data `path` holds, beyond its path: a dataset folder's
    `tt.tokens.store.dataset_fingerprint` (its generating config and a digest of its shards'
    manifests), or an episode token file's size and BLAKE2b digest. A resumed ``tt train``
    compares it with its run's (`describe_data_change`)."""
    path = Path(path)
    if is_dataset(path) or path.is_dir():  # a folder is read as a dataset, which says what it lacks
        from tt.tokens.store import dataset_fingerprint

        return dataset_fingerprint(path)
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return {"kind": "file", "bytes": path.stat().st_size, "digest": h.hexdigest()}


def describe_data_change(before: dict, now: dict) -> str | None:
    """None when two `data_identity` values are of the same data, else how the data changed
    (for a message: "it was regenerated with other arguments: --seed 0 then, 1 now")."""
    if before == now:
        return None
    if before.get("kind") != now.get("kind"):
        return f"it is now {'a dataset folder' if now.get('kind') == 'dataset' else 'an episode token file'}"
    if now.get("kind") == "dataset":
        a, b = before.get("config") or {}, now.get("config") or {}
        changed = [k for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
        if changed:
            return "it was regenerated with other arguments: " + ", ".join(
                f"--{k.replace('_', '-')} {a.get(k)} then, {b.get(k)} now" for k in changed[:4]
            )
        if before.get("shards") != now.get("shards"):
            return f"its shards changed: {before.get('shards')} then, {now.get('shards')} now"
        return "its shards' content changed since (regenerated or replaced)"
    if before.get("bytes") != now.get("bytes"):
        return f"its content changed: {before.get('bytes')} bytes then, {now.get('bytes')} now"
    return "its content changed since (another file of the same size)"


def open_token_source(path: str | Path, **kwargs):
    """Training data at `path`: a `StoreTokenSource` for a dataset folder (``tt generate``),
    else a `tt.dit.data.EpisodeTokens` file. Keyword arguments go to `StoreTokenSource`. A
    folder is read as a dataset, whose reader says what it lacks (a damaged root, say)."""
    if is_dataset(path) or Path(path).is_dir():
        return StoreTokenSource(path, **kwargs)
    from tt.dit.data import EpisodeTokens

    return EpisodeTokens.load(path)


__all__ = [
    "EpisodeWindows",
    "SE2Augment",
    "StoreTokenSource",
    "WINDOW_KINDS",
    "augment_se2_tokens",
    "data_identity",
    "describe_data_change",
    "make_loader",
    "open_token_source",
    "window_steps",
]
