"""`tt generate`: RoboToken datasets at scale, resumable, sharded, distributable.

A dataset of N designs x K episodes is cut into shards of `GenerateConfig.designs_per_shard`
designs. Shard i is a pure function of (config, i): its designs, the motion and SE(2)
augmentation of every episode, and CMA-ES seeds all derive from
``SeedSequence([seed, i, stream, ...])``, and the rollout is deterministic on the CPU. So
shards can be generated in any order, by any number of processes or Ray workers, and a run
that was killed resumes by generating exactly the shards that are missing or damaged: the
result equals an uninterrupted run's, bit for bit.

One shard:
1. designs: sampled uniformly from the space, or (``bias="cmaes"``, the paper's data
   biasing) every design CMA-ES samples with population 5 for 3 generations on training
   motions, one run per motion, cycling through the training set;
2. episodes: designs are rolled out in groups of `group_designs`; each group draws K
   distinct training motions, each under its own random planar transform
   (`tt.sim.motions.augment_motion`), and every design of the group runs all K of them
   (one batched rollout of group x K worlds) under the paper's control perturbation: the
   actuators execute the controller's command plus Gaussian noise of `action_noise` [rad or
   m] per actuator and step, the clean command is logged (`tt.sim.rollout.rollout`);
3. filter: episodes shorter than `min_steps` control steps (the rollout terminated them:
   the end effector left the target by more than the space's threshold) or with non-finite
   states are dropped and counted by reason; with ``select`` > 1 each motion of the group
   then keeps only the episodes `tt.tokens.draws.select_episodes` picks by reward (its
   designs chosen for that motion, a ``uniform_share`` drawn uniformly), the others are
   counted as "unselected";
4. tokenize: embodiment tokens per design, dynamics and target tokens of every executed
   step (states and actuator forces / velocities of the perturbed execution, control tokens
   from the clean commands, ``Episode.action``), padded to the design space's maxima
   (`space_token_maxima`); a group's kept episodes are stored in a seeded random order, so
   that a block of consecutive episodes (the unit loaders read) mixes the group's robots;
5. write: appended to a shard under ``.partial/``, then checksummed and renamed into
   ``shards/`` (`tt.tokens.store.ShardWriter`).

Control perturbation: the paper adds perturbations to the expert's actions "to increase state
diversity, but log the unperturbed expert action for supervision" (after PDP, Truong et al.
2024) without giving their size; the authors' data generator adds i.i.d. Gaussian noise to
the joint position commands, off (0) in its shipped configs. tt's default, 0.01 rad, was
measured on 48 random ViperX designs x 3 training motions (250 steps, CPU): it leaves the
kept fraction (114 of 144) and the median tracking error (13.6 cm) of the clean rollouts
unchanged and moves the median world's joints 0.013 rad (end effector 0.6 cm) off its clean
trajectory; it also raises the median world's mean actuator speed from 0.14 to 0.24 rad/s
(jitter of the noise), which larger sigma inflates further (0.05 rad: 0.73 rad/s, tracking
error +0.3 cm). ``action_noise=0`` generates unperturbed episodes (``Episode.action`` is then
``Episode.ctrl``).
"""

from __future__ import annotations

import errno
import json
import logging
import os
import shutil
import time
import uuid
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np
import torch

from tt.kernels.errors import TTError
from tt.tokens.draws import (
    _STREAM_CMAES,
    _STREAM_DESIGNS,
    _STREAM_EPISODES,
    _STREAM_NOISE,
    _STREAM_SELECT,
    BIASES,
    DEFAULT_ACTION_NOISE,
    GenerateConfig,
    _rng,
    _seed_int,
    episode_motion,
    finite_worlds,
    select_episodes,
    space_token_maxima,
    training_motions,
)
from tt.tokens.info import format_bytes
from tt.tokens.lock import DatasetLock
from tt.tokens.schema import EMBODIMENT_TYPES, SCHEMA
from tt.tokens.store import (
    DatasetError,
    ShardPart,
    ShardWriter,
    check_shards,
    clear_partial,
    create_root,
    discard_shard,
    is_dataset,
    merge_stats,
    normalizer_from_stats,
    read_manifest,
    read_root,
    root_damage,
    shard_dirs,
    shard_name,
    update_root,
    verify_shard,
)

logger = logging.getLogger(__name__)

#: Worlds tokenized at once (bounds the memory of all-step token tensors).
_TOKENIZE_WORLDS = 256
#: Stages timed per shard, in pipeline order.
STAGES = ("designs", "rollout", "score", "tokenize", "write")


# ------------------------------------------------------------------------------ one shard
def shard_design_list(
    config: GenerateConfig, index: int, *, device: str | None = None, threads: int | None = None
) -> list:
    """The designs of shard `index` (a pure function of config and index)."""
    from tt.sim.designs import get_space

    n = config.shard_designs(index)
    sp = get_space(config.space)
    if config.bias is None:
        return sp.sample(n, seed=_seed_int(config.seed, index, _STREAM_DESIGNS))
    return _cmaes_designs(config, index, n, device, threads)


def _cmaes_designs(config: GenerateConfig, index: int, n: int, device: str | None, threads: int | None = None) -> list:
    """Every design CMA-ES samples in ceil(n / (popsize x generations)) runs, run j of shard i
    on training motion (i * runs_per_full_shard + j) mod M, so consecutive shards walk the
    whole training set."""
    from tt.baselines import CMAES, CMAESConfig, Problem

    per_run = config.cmaes_popsize * config.cmaes_generations
    runs = -(-n // per_run)
    first = index * -(-config.designs_per_shard // per_run)
    base = training_motions(config.space)
    by_motion: dict[int, int] = {}
    for j in range(runs):
        m = (first + j) % len(base)
        by_motion[m] = by_motion.get(m, 0) + 1
    optimizer = CMAES(CMAESConfig(popsize=config.cmaes_popsize, generations=config.cmaes_generations))
    designs = []
    for m, count in by_motion.items():
        motion = episode_motion(replace(config, max_yaw=0.0, max_shift=0.0), base[m], 0)
        # Runs on one motion go in lock step (CMA-ES restarts), one batched rollout per generation.
        problem = Problem(
            space=config.space,
            motions=(motion,),
            reward=config.reward,
            budget=per_run * count,
            threads=threads,
            seed=_seed_int(config.seed, index, _STREAM_CMAES, m, bits=21),
            backend=config.backend,
            device=device,
        )
        designs += optimizer.optimize(problem).designs
    return designs[:n]


def _select_worlds(ep, worlds: torch.Tensor):
    """The Episode restricted to `worlds` (copies)."""
    from tt.sim.episode import Episode

    w = worlds.to(ep.qpos.device)
    kw = {f.name: getattr(ep, f.name)[w] for f in fields(Episode) if f.name != "dt"}
    return Episode(**kw, dt=ep.dt)


def _pad_last(x: np.ndarray, axis: int, size: int, what: str) -> np.ndarray:
    cur = x.shape[axis]
    if cur > size:
        raise DatasetError(
            f"{what} has {cur} tokens, more than the design space's maximum {size}; "
            "the maxima stored with the dataset are wrong"
        )
    if cur == size:
        return x
    pad = [(0, 0)] * x.ndim
    pad[axis] = (0, size - cur)
    return np.pad(x, pad)


def _design_arrays(designs: Sequence, widths: Mapping[str, int]) -> tuple[np.ndarray, np.ndarray]:
    disc = np.full((len(designs), widths["discrete"]), -1, np.int16)
    cont = np.full((len(designs), widths["continuous"]), np.nan, np.float64)
    for i, d in enumerate(designs):
        disc[i, : len(d.discrete)] = d.discrete
        cont[i, : len(d.continuous)] = d.continuous
    return disc, cont


@dataclass
class ShardResult:
    """What generating one shard did: counts, bytes, wall seconds per stage, CPU seconds of
    the process (all its threads) over the whole shard."""

    index: int
    generated: int
    kept: int
    dropped: dict[str, int]
    steps: int
    bytes: int
    seconds: dict[str, float]
    cpu_seconds: float
    device: str

    def to_dict(self) -> dict:
        return asdict(self)


def _store_pool(threads: int | None, device: str):
    """A one-thread pool that tokenizes and writes a group while the next rolls out, where
    the rollouts run on the CPU and may use more than one thread (None: every core); else
    no pool (None). On a GPU the store's torch work would run during the next rollout's
    graph capture, so there it stays inline."""
    from concurrent.futures import ThreadPoolExecutor
    from contextlib import nullcontext

    from tt.kernels.rollout import cpu_threads

    on_cpu = str(device).startswith("cpu")
    return (
        ThreadPoolExecutor(1, thread_name_prefix="tt-store") if on_cpu and cpu_threads(threads) > 1 else nullcontext()
    )


def generate_shard(
    config: GenerateConfig,
    index: int,
    out: str | Path,
    *,
    device: str,
    widths: Mapping,
    progress: Callable[[int], None] | None = None,
    tokenizer=None,
    threads: int | None = None,
) -> ShardResult:
    """Generate shard `index` of the dataset at `out` (whose root exists) and commit it.

    widths: ``space_token_maxima(config.space)`` as stored in the root. progress: called with
    the number of episodes rolled out after each group. threads: CPU threads of the "warp"
    rollouts (None: every core; the shard is the same for every count). Returns the shard's
    `ShardResult`.
    """
    from tt.sim.designs import get_space
    from tt.sim.rewards import RewardInputs, get_reward, metrics
    from tt.sim.rollout import rollout
    from tt.tokens.episodes import episode_tokens
    from tt.tokens.tokenize import Tokenizer

    tokenizer = tokenizer if tokenizer is not None else Tokenizer()
    maxima = {k: int(v) for k, v in widths["maxima"].items()}
    static_len = {n: maxima[n] for n in EMBODIMENT_TYPES if maxima.get(n, 0) > 0}
    step_types = [n for n in SCHEMA.names() if n not in EMBODIMENT_TYPES and maxima.get(n, 0) > 0]
    sp = get_space(config.space)
    K = config.episodes_per_design
    base = training_motions(config.space)
    reward_cfg = get_reward(config.reward, config.space)
    seconds = {s: 0.0 for s in STAGES}
    dropped = {"short": 0, "nonfinite": 0}
    cpu0 = time.process_time()
    t0 = time.perf_counter()
    designs = shard_design_list(config, index, device=device, threads=threads)
    seconds["designs"] += time.perf_counter() - t0
    first_episode = index * config.designs_per_shard * K
    generated = 0

    def store(group, models, ep, motions, motion_ids, aug_seeds, g0, keep, lengths, score) -> None:
        """Tokenize a group's kept episodes and append them to the shard (in group order)."""
        t = time.perf_counter()
        emb = tokenizer(models)
        static_tb = emb.tokens.pad_to(static_len)
        static = {n: (static_tb.values[n], static_tb.ids[n], static_tb.mask[n]) for n in static_len}
        steps: dict[str, list] = {}
        for c0 in range(0, len(keep), _TOKENIZE_WORLDS):
            chunk = keep[c0 : c0 + _TOKENIZE_WORLDS]
            sub = _select_worlds(ep, torch.as_tensor(chunk))
            ln = lengths[chunk]
            tmax = int(ln.max())
            tb = episode_tokens(sub, emb.index, step_index=torch.arange(tmax).expand(len(chunk), tmax))
            rows = np.arange(tmax)[None, :] < ln[:, None]  # (w, tmax)
            for name in tb.types:
                v = tb.values[name].cpu().numpy()
                p = v.shape[1] // tmax
                v = v.reshape(len(chunk), tmax, p, -1)[rows]  # (S, p, width)
                ids = tb.ids[name].cpu().numpy().reshape(len(chunk), tmax, p, -1)[:, 0]
                ids[..., SCHEMA[name].ids.index("time")] = 0
                mask = tb.mask[name].cpu().numpy().reshape(len(chunk), tmax, p)[:, 0]
                if not np.isfinite(v).all():
                    raise FloatingPointError(f"shard {index}: non-finite {name} tokens from finite episodes")
                size = maxima[name]
                steps.setdefault(name, []).append(
                    (_pad_last(v, 1, size, name), _pad_last(ids, 1, size, name), _pad_last(mask, 1, size, name))
                )
        step_arrays = {n: tuple(np.concatenate([c[k] for c in parts]) for k in range(3)) for n, parts in steps.items()}
        # A type none of this group's robots has still needs its rows (all padding), so
        # every per-step array of the shard stays aligned with the episode index.
        n_steps = int(lengths[keep].sum())
        for name in step_types:
            if name not in step_arrays:
                spec = SCHEMA[name]
                step_arrays[name] = (
                    np.zeros((n_steps, maxima[name], spec.width), np.float32),
                    np.zeros((len(keep), maxima[name], len(spec.ids)), np.int64),
                    np.zeros((len(keep), maxima[name]), bool),
                )
        seconds["tokenize"] += time.perf_counter() - t

        t = time.perf_counter()
        d_local = ep.design_index.cpu().numpy()[keep]
        m_local = ep.motion_index.cpu().numpy()[keep]
        se2 = np.array([[motions[j].meta["se2"][k] for k in ("yaw", "dx", "dy")] for j in range(K)], np.float64)
        episode = {
            "episode_id": first_episode + (g0 + d_local) * K + m_local,
            "design": d_local,
            "motion": motion_ids[m_local].astype(np.int32),
            "augment_seed": aug_seeds[m_local].astype(np.int64),
            "se2": se2[m_local],
            "length": lengths[keep],
            "motion_steps": np.array([m.steps for m in motions], np.int32)[m_local],
            "reward": score["reward"][keep].astype(np.float32),
            "pos_err": score["pos_err"][keep].astype(np.float32),
            "orn_err": score["orn_err"][keep].astype(np.float32),
            "survival": score["survival"][keep] > 0.5,
        }
        disc, cont = _design_arrays(group, widths)
        writer.append(ShardPart(disc, cont, static, episode, step_arrays))
        seconds["write"] += time.perf_counter() - t

    with ShardWriter(out, index) as writer, _store_pool(threads, device) as pool:
        pending = None
        for g0 in range(0, len(designs), config.group_designs):
            group = designs[g0 : g0 + config.group_designs]
            t = time.perf_counter()
            rng = _rng(config.seed, index, _STREAM_EPISODES, g0)
            motion_ids = rng.choice(len(base), size=K, replace=K > len(base))
            aug_seeds = rng.integers(0, 2**31, size=K)
            motions = [episode_motion(config, base[m], s) for m, s in zip(motion_ids, aug_seeds)]
            # Models are built once (a few ms per robot) for the tokenizer and the rollout; on
            # warp a space that builds tree fields directly rolls those out instead, as every
            # warp rollout of Designs does, so `rollout(designs)` replays a shard bit for bit.
            models = [sp.model(d) for d in group]
            trees = sp.trees(group) if config.backend == "warp" else None
            ep = rollout(
                models if trees is None else trees,
                motions,
                backend=config.backend,
                device=device,
                action_noise=config.action_noise,
                threads=threads,
                noise_seed=_seed_int(config.seed, index, _STREAM_NOISE, g0),
            )
            seconds["rollout"] += time.perf_counter() - t

            t = time.perf_counter()
            W = ep.worlds
            dev = ep.ee_pos.device
            motion_steps = torch.tensor([m.steps for m in motions], device=dev)[ep.motion_index.to(dev)]
            # Summed in float64, so the float32 values stored do not depend on the summation
            # order (thread count) of the worker that computed them.
            inputs = RewardInputs.from_episode(ep, motion_steps=motion_steps, double=True)
            score = {k: v.cpu().numpy() for k, v in metrics(inputs, reward_cfg).items()}
            lengths = ep.lengths().cpu().numpy().astype(np.int64)
            finite = finite_worlds(ep)
            short = lengths < config.min_steps
            dropped["nonfinite"] += int((~finite).sum())
            dropped["short"] += int((finite & short).sum())
            # Stored in random order: a block of consecutive episodes (what loaders read at once)
            # then holds many robots, not the K episodes of a few.
            eligible = finite & ~short
            if config.select > 1:
                eligible &= select_episodes(
                    score["reward"],
                    ep.motion_index.cpu().numpy(),
                    eligible,
                    config.group_keep(len(group)),
                    config.uniform_share,
                    _rng(config.seed, index, _STREAM_SELECT, g0),
                )
                dropped["unselected"] = dropped.get("unselected", 0) + int((finite & ~short).sum() - eligible.sum())
            keep = rng.permutation(np.nonzero(eligible)[0])
            generated += W
            seconds["score"] += time.perf_counter() - t

            if pool is None:
                store(group, models, ep, motions, motion_ids, aug_seeds, g0, keep, lengths, score)
            else:
                # One group in flight: its tokens are written while the next group rolls out.
                if pending is not None:
                    pending.result()
                pending = pool.submit(
                    store, group, models, ep, motions, motion_ids, aug_seeds, g0, keep, lengths, score
                )
            if progress is not None:
                progress(W)
        if pending is not None:
            pending.result()
        t = time.perf_counter()
        attrs = {"generated": generated, "dropped": dropped, "device": "cpu" if device == "cpu" else "cuda"}
        folder = writer.commit(attrs)  # timings stay out of the files: a resumed dataset is byte-identical
        seconds["write"] += time.perf_counter() - t
    manifest = read_manifest(folder)
    size = sum(v[0] for v in manifest["files"].values())
    return ShardResult(
        index, generated, writer.episodes, dropped, writer.steps, size, seconds, time.process_time() - cpu0, device
    )


def _shard_task(config: dict, index: int, out: str, device: str, widths: dict, queue=None, threads: int = 1) -> dict:
    """Worker entry point (process pool or Ray task): one shard, results as a dict."""
    cfg = GenerateConfig.from_dict(config)
    report = None if queue is None else queue.put
    return generate_shard(cfg, index, out, device=device, widths=widths, progress=report, threads=threads).to_dict()


def _init_worker(parent: int) -> None:
    """A pool worker's start: it dies with the run that started it (`parent`: SIGKILL of
    ``tt generate`` leaves no worker writing shards), and runs one torch thread (the workers
    are the parallelism)."""
    from tt.kernels.processes import die_with_parent

    die_with_parent(parent)
    torch.set_num_threads(1)


# ------------------------------------------------------------------------------ the run
@dataclass
class GenerateReport:
    """Totals of the dataset and what this run did.

    totals: designs, generated, kept, dropped (by reason), steps, bytes, shards (complete).
    run: shards generated by this run, damaged shards regenerated, wall seconds, episodes
    rolled out per second, seconds per stage summed over this run's shards (per worker),
    CPU seconds of the shards' processes.
    """

    path: str
    totals: dict
    run: dict
    shard_results: list[dict] = field(default_factory=list)

    def text(self) -> str:
        t, r = self.totals, self.run
        drops = ", ".join(f"{v:,} {k}" for k, v in sorted(t["dropped"].items()) if v) or "none"
        lines = [
            f"dataset {self.path}: {t['shards']} shards, {t['designs']:,} designs, {t['kept']:,} episodes kept of "
            f"{t['generated']:,} generated (dropped: {drops}), {t['steps']:,} steps, {format_bytes(t['bytes'])}"
        ]
        if r["shards"]:
            stage = r["stage_seconds"]
            total = sum(stage.values()) or 1.0
            split = ", ".join(f"{k} {100 * v / total:.0f}%" for k, v in stage.items())
            lines.append(
                f"this run: {r['shards']} shards ({r['episodes']:,} episodes) in {r['seconds']:.1f} s = "
                f"{r['episodes_per_second']:.1f} episodes/s; time per stage: {split}"
            )
        else:
            lines.append("this run: nothing to do, every shard was already complete")
        if r["regenerated"]:
            lines.append(
                "regenerated damaged shards: " + "; ".join(f"{k}: {v}" for k, v in sorted(r["regenerated"].items()))
            )
        if r.get("repaired_root"):
            lines.append(r["repaired_root"])
        return "\n".join(lines)


def _check_config(stored: Mapping, wanted: Mapping, path: Path) -> None:
    for k, v in wanted.items():
        if k in stored and stored[k] != v:
            raise DatasetError(
                f"{path} was generated with {k}={stored[k]!r}, this run asks for {k}={v!r}; "
                "re-run with the dataset's arguments to resume it, or choose another --out"
            )
    missing = [k for k in wanted if k not in stored]
    if missing:
        raise DatasetError(f"{path} has no stored value for {missing}; it was written by another tt version")


def _open_or_create(
    config: GenerateConfig, out: Path, *, device: str = "cpu", threads: int | None = None
) -> tuple[dict, str | None]:
    """The root attributes of dataset `out` for `config`: read (the stored config must be
    `config`), created, or rebuilt: a root ``zarr.json`` that is damaged (`root_damage`) or
    missing beside shards is written anew from `config` when the intact shards agree with it
    (`_adopt_shards`; else a `DatasetError`). Returns (attrs, what was repaired or None)."""
    wanted = config.to_dict()
    meta = out / "zarr.json"
    damage = root_damage(out)
    if damage is None and is_dataset(out):
        attrs = read_root(out)
        _check_config(attrs.get("config", {}), wanted, out)
        return attrs, None
    others = [
        p.name
        for p in out.iterdir()
        if p.name not in (".lock", ".partial", "shards") and not (damage is not None and p.name == "zarr.json")
    ]
    if others:
        raise DatasetError(
            f"{out} exists and is not a tt dataset (it holds {sorted(others)[:5]}); choose an empty or new folder"
        )
    widths = space_token_maxima(config.space)
    shards = shard_dirs(out)
    repaired = None
    if damage is not None or shards:
        what = (
            f"{meta}, the dataset's root, is damaged ({damage})"
            if damage is not None
            else f"{meta}, the dataset's root, is missing"
        )
        repaired = f"{what}; rebuilt it from these arguments" + _adopt_shards(
            config, out, shards, widths, what, device, threads
        )
        logger.warning("%s", repaired)
    motions = [m.name for m in training_motions(config.space)]
    attrs = {
        "space": config.space,
        "config": wanted,
        "maxima": widths["maxima"],
        "design_widths": {"discrete": widths["discrete"], "continuous": widths["continuous"]},
        "maxima_source": widths["source"],
        "motions": motions,
        "complete": False,
    }
    if damage is None:
        create_root(out, attrs)
    else:  # written beside, then renamed over the damaged file: a crash leaves one or the other
        scratch = out / ".partial" / f"root-{uuid.uuid4().hex[:8]}"
        create_root(scratch, attrs)
        os.replace(scratch / "zarr.json", meta)
        shutil.rmtree(scratch, ignore_errors=True)
    return read_root(out), repaired


def _adopt_shards(
    config: GenerateConfig,
    out: Path,
    shards: Mapping[int, Path],
    widths: Mapping,
    what: str,
    device: str,
    threads: int | None,
) -> str:
    """Check that the shards of `out`, whose root is lost, were generated with `config`
    before a root of `config` is written over them: every intact shard's records
    (`_shard_disagreement`), and, where this run's device is the kind the shards were
    generated on (rollouts are deterministic per kind), the smallest intact shard regenerated
    byte for byte (its manifest). Raises `DatasetError` naming the first disagreement;
    returns the rest of the repair note (what was checked)."""
    intact = {i: f for i, f in sorted(shards.items()) if verify_shard(f, full=False) is None}
    for i, folder in intact.items():
        why = _shard_disagreement(config, i, folder, widths)
        if why is not None:
            raise DatasetError(
                f"{what}, and its shard {folder.name} {why}, so it was not generated with these arguments "
                "and the root cannot be rebuilt from them; re-run the `tt generate` command that wrote "
                "the dataset (its arguments were in the lost root), or choose another --out"
            )
    if not intact:
        return " (no intact shard to check them against)"
    note = f" (the intact shards, {len(intact)}, agree with them: counts, designs and seeded draws"
    index = min(intact, key=lambda i: (config.shard_designs(i), i))
    folder = intact[index]
    recorded = json.loads((folder / "zarr.json").read_text())["attributes"].get("device")
    here = "cpu" if device == "cpu" else "cuda"
    if recorded != here:
        return note + f"; not re-simulated: they were generated on {recorded}, this run is on {here})"
    scratch = out / ".partial" / f"check-{folder.name}-{uuid.uuid4().hex[:8]}"
    scratch.mkdir(parents=True)
    try:
        generate_shard(config, index, scratch, device=device, widths=widths, threads=threads)
        again = read_manifest(scratch / "shards" / folder.name)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    stored = read_manifest(folder)
    if again != stored:
        differ = sorted(
            k for k in set(again["files"]) | set(stored["files"]) if again["files"].get(k) != stored["files"].get(k)
        )
        raise DatasetError(
            f"{what}, and its shard {folder.name} regenerated with these arguments differs from the stored "
            f"one ({', '.join(differ[:3])}), so it was not generated with them (action_noise, bias, "
            "min_steps, ...) and the root cannot be rebuilt from them; re-run the `tt generate` command "
            "that wrote the dataset (its arguments were in the lost root), or choose another --out"
        )
    return note + f"; shard {folder.name} regenerated byte for byte)"


def _shard_disagreement(config: GenerateConfig, index: int, folder: Path, widths: Mapping) -> str | None:
    """What intact shard `index` records that `config` would not have generated, or None:
    its shard count, design and rolled-out episode counts, selection, design widths, its
    designs where they are uniform draws, each kept episode's motion and augmentation seed
    (the config's seeded draws) and lengths against the minimum. No simulation."""
    from tt.tokens.store import ShardReader

    if index >= config.shards:
        return (
            f"is shard {index}, but --designs {config.designs} in shards of designs_per_shard "
            f"{config.designs_per_shard} make {config.shards}"
        )
    r = ShardReader(folder)
    a = r.attrs
    n, K = config.shard_designs(index), config.episodes_per_design
    if int(a["designs"]) != n:
        return f"holds {a['designs']} designs, these arguments give it {n} (--designs, designs_per_shard)"
    if int(a["generated"]) != n * K:
        return (
            f"rolled out {a['generated']} episodes, these arguments {n * K} ({n} designs x --episodes-per-design {K})"
        )
    if ("unselected" in a.get("dropped", {})) != (config.select > 1):
        return "was generated " + ("without select" if config.select > 1 else "with select above 1")
    disc, cont = r._read("design/discrete"), r._read("design/continuous")
    if disc.shape[1] != widths["discrete"] or cont.shape[1] != widths["continuous"]:
        return f"holds designs of another design space than --space {config.space}"
    if config.bias is None:
        want = _design_arrays(shard_design_list(config, index), widths)
        if not (np.array_equal(disc, want[0]) and np.array_equal(cont, want[1], equal_nan=True)):
            return "holds other designs than these arguments draw (--seed, bias, --space)"
    if r.episodes:
        local = r.field("episode_id").astype(np.int64) - index * config.designs_per_shard * K
        if local.min() < 0 or local.max() >= n * K:
            return "numbers its episodes as other designs_per_shard or --episodes-per-design do"
        row, slot = local // K, local % K
        group = row // config.group_designs * config.group_designs
        count = len(training_motions(config.space))
        for g0 in np.unique(group):
            rng = _rng(config.seed, index, _STREAM_EPISODES, int(g0))
            motion_ids = rng.choice(count, size=K, replace=K > count)
            aug_seeds = rng.integers(0, 2**31, size=K)
            sel = group == g0
            if not (
                np.array_equal(r.field("motion")[sel], motion_ids[slot[sel]])
                and np.array_equal(r.field("augment_seed")[sel], aug_seeds[slot[sel]])
            ):
                return "holds episodes on other motions than these arguments draw (--seed, --episodes-per-design)"
        if int(r.field("length").min()) < config.min_steps:
            return f"keeps episodes of {int(r.field('length').min())} control steps, below min_steps {config.min_steps}"
    return None


def _widths(attrs: Mapping) -> dict:
    return {"maxima": attrs["maxima"], **attrs["design_widths"]}


def generate(
    config: GenerateConfig,
    out: str | Path,
    *,
    device: str | None = None,
    workers: int = 1,
    ray_address: str | None = None,
    progress: bool = True,
    verify: str = "full",
    threads: int | None = None,
) -> GenerateReport:
    """Generate (or resume) the dataset of `config` in folder `out`; see the module docstring.

    device: Warp/torch device of the rollouts (None: `tt.kernels.device.default_device()`).
    workers: processes generating shards at once (with ``ray_address="local"``: the local
    Ray cluster's CPUs). ray_address: None (no Ray), "local" (start a local cluster) or a
    cluster address ("ray://host:10001", "auto"); `out` must then be on a file system every
    worker sees. threads: CPU threads of each worker process's "warp" rollouts (None: the
    cores shared out over the workers; Ray tasks, which reserve one CPU each, use one); the
    dataset is the same for every count. verify: how existing shards are checked ("full": sizes and CRC-32, "size").
    Raises `DatasetError` when `out` holds another config or is not a dataset.
    """
    from tt.kernels.device import resolve_device
    from tt.kernels.rollout import cpu_threads

    if workers < 1:
        raise TTError(f"workers must be >= 1, got {workers}")
    threads = cpu_threads(threads) if threads is not None else max(1, cpu_threads() // workers)
    if verify not in ("size", "full"):
        raise TTError(f"verify must be 'size' or 'full', got {verify!r}")
    device = resolve_device(device)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with DatasetLock(out):
        attrs, repaired = _open_or_create(config, out, device=device, threads=threads)
        clear_partial(out)
        widths = _widths(attrs)
        done: dict[int, dict] = {}
        regenerated: dict[int, str] = {}
        for i, why in check_shards(out, shards=config.shards, full=verify == "full").items():
            folder = out / "shards" / shard_name(i)
            if why is None:
                done[i] = _shard_attrs(folder)
            else:
                logger.warning("shard %s is damaged (%s); regenerating it", folder.name, why)
                regenerated[i] = why
                discard_shard(out, i)
        todo = [i for i in range(config.shards) if i not in done]
        total = config.designs * config.episodes_per_design
        initial = sum(int(a["generated"]) for a in done.values())
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(
                total=total,
                initial=initial,
                desc=f"generate {config.space}",
                unit="ep",
                dynamic_ncols=True,
                smoothing=0.05,
            )
        results: list[dict] = []
        try:
            if todo and ray_address is not None:
                results = _run_ray(config, todo, out, device, widths, workers, ray_address, bar)
            elif todo and workers > 1:
                results = _run_pool(config, todo, out, device, widths, workers, bar, threads)
            else:
                for i in todo:
                    results.append(
                        generate_shard(
                            config,
                            i,
                            out,
                            device=device,
                            widths=widths,
                            threads=threads,
                            progress=bar.update if bar is not None else None,
                        ).to_dict()
                    )
        except OSError as e:
            if e.errno not in (errno.ENOSPC, errno.EDQUOT):
                raise
            kept = sum(verify_shard(f, full=False) is None for f in shard_dirs(out).values())
            raise DatasetError(
                f"{e.strerror} while writing {out} ({e.filename or 'a shard'}): {kept} of {config.shards} shards "
                "are complete and kept, the one being written is discarded on the next run; free space, "
                "then re-run the same command to resume"
            ) from None
        finally:
            if bar is not None:
                bar.close()
        for r in results:
            done[r["index"]] = _shard_attrs(out / "shards" / f"s{r['index']:06d}")
        if len(done) == config.shards and not attrs.get("complete"):
            stats = merge_stats(a["stats"] for a in done.values())
            update_root(
                out,
                {"complete": True, "normalizer": normalizer_from_stats(stats).to_dict(), "totals": _totals(done, out)},
            )
        totals = _totals(done, out)
    seconds = time.perf_counter() - start
    stage = {s: sum(r["seconds"][s] for r in results) for s in STAGES}
    episodes = sum(r["generated"] for r in results)
    run = {
        "shards": len(results),
        "episodes": episodes,
        "seconds": seconds,
        "cpu_seconds": sum(r["cpu_seconds"] for r in results),
        "episodes_per_second": episodes / seconds if seconds > 0 else 0.0,
        "stage_seconds": stage,
        "regenerated": regenerated,
        "workers": workers,
        "ray": ray_address,
        "device": device,
        "repaired_root": repaired,
    }
    return GenerateReport(str(out), totals, run, results)


def _shard_attrs(folder: Path) -> dict:
    import json

    attrs = json.loads((folder / "zarr.json").read_text())["attributes"]
    attrs["bytes"] = sum(v[0] for v in read_manifest(folder)["files"].values())
    return attrs


def _totals(done: Mapping[int, dict], out: Path) -> dict:
    dropped: dict[str, int] = {}
    for a in done.values():
        for k, v in a.get("dropped", {}).items():
            dropped[k] = dropped.get(k, 0) + int(v)
    return {
        "shards": len(done),
        "designs": sum(int(a["designs"]) for a in done.values()),
        "generated": sum(int(a["generated"]) for a in done.values()),
        "kept": sum(int(a["episodes"]) for a in done.values()),
        "dropped": dropped,
        "steps": sum(int(a["steps"]) for a in done.values()),
        "bytes": sum(int(a["bytes"]) for a in done.values()),
    }


def _run_pool(config, todo, out, device, widths, workers, bar, threads: int) -> list[dict]:
    import multiprocessing as mp
    from multiprocessing.managers import SyncManager

    from tt.kernels.processes import die_with_parent

    ctx = mp.get_context("spawn")  # fork would copy Warp/torch thread state
    manager = SyncManager(ctx=ctx)
    manager.start(die_with_parent, (os.getpid(),))  # the progress queue's server dies with this run too
    with manager:
        queue = manager.Queue()
        results = []
        with ProcessPoolExecutor(
            max_workers=workers, mp_context=ctx, initializer=_init_worker, initargs=(os.getpid(),)
        ) as pool:
            pending = {
                pool.submit(_shard_task, config.to_dict(), i, str(out), device, widths, queue, threads) for i in todo
            }
            try:
                while pending:
                    finished, pending = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
                    _drain(queue, bar)
                    for f in finished:
                        results.append(f.result())
            except BaseException:
                for f in pending:
                    f.cancel()
                raise
            _drain(queue, bar)
    return results


def _drain(queue, bar) -> None:
    import queue as q

    while True:
        try:
            n = queue.get_nowait()
        except (q.Empty, EOFError, OSError):
            return
        if bar is not None:
            bar.update(n)


def _drain_ray(queue, bar) -> None:
    n = queue.size()
    if n and bar is not None:
        bar.update(sum(queue.get_nowait_batch(n)))


def _run_ray(config, todo, out, device, widths, workers, address, bar) -> list[dict]:
    try:
        import ray
    except ImportError:
        raise DatasetError("ray needs Ray: pip install 'tt[ray]'") from None
    started = False
    if not ray.is_initialized():
        if address == "local":
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False, configure_logging=False)
        else:
            ray.init(address=address, log_to_driver=False, configure_logging=False)
        started = True
    try:
        from ray.util.queue import Queue

        gpus = 1 if str(device).startswith("cuda") else 0
        task = ray.remote(num_cpus=1, num_gpus=gpus, max_retries=2)(_shard_task)
        queue = Queue(actor_options={"num_cpus": 0})  # episodes done, reported after every group
        out_abs = str(Path(out).resolve())
        pending = [task.remote(config.to_dict(), i, out_abs, device, widths, queue) for i in todo]
        results = []
        while pending:
            finished, pending = ray.wait(pending, num_returns=1, timeout=0.5)
            _drain_ray(queue, bar)
            results += ray.get(finished)
        _drain_ray(queue, bar)
        return results
    finally:
        if started:
            ray.shutdown()


# ------------------------------------------------------------------------------ tt generate
def generate_cmd(
    space: str,
    designs: int,
    out: str | Path,
    *,
    episodes_per_design: int = 10,
    device: str | None = None,
    workers: int = 1,
    bias: str | None = None,
    seed: int = 0,
    ray: str | None = None,
    designs_per_shard: int = 1024,
    min_steps: int = 100,
    max_motion_steps: int | None = None,
    action_noise: float | None = None,
    progress: bool = True,
    threads: int | None = None,
    select: int = 1,
    uniform_share: float = 0.0,
) -> str:
    """``tt generate --space S --designs N --episodes-per-design K --out DATASET [--device D]
    [--workers W] [threads T] [bias cmaes] [--seed S] [ray ADDRESS|local] [action_noise SIGMA]
    [select K [uniform_share F]]``.

    The rollout backend is `tt.sim.backends.default_backend` of the space: "warp" for
    contact-free spaces, "mjbatch" (the oracle's MuJoCo C physics on every thread) for the
    quadruped. action_noise None: `tt.tokens.draws.default_action_noise` of the backend (mjbatch perturbs
    when given a sigma). Generates or resumes the
    dataset and returns the summary text. Raises ValueError for bad arguments and
    `DatasetError` when DATASET holds a dataset of other arguments.
    """
    from tt.sim.backends import default_backend
    from tt.tokens.draws import default_action_noise

    # tt's kernels for contact-free spaces, MuJoCo C batched for spaces with contacts (the quadruped).
    backend = default_backend(space)
    if action_noise is None:
        action_noise = default_action_noise(backend)
    config = GenerateConfig(
        space=space,
        designs=designs,
        episodes_per_design=episodes_per_design,
        seed=seed,
        designs_per_shard=designs_per_shard,
        bias=bias,
        min_steps=min_steps,
        max_motion_steps=max_motion_steps,
        backend=backend,
        action_noise=action_noise,
        select=select,
        uniform_share=uniform_share,
    )
    report = generate(config, out, device=device, workers=workers, ray_address=ray, progress=progress, threads=threads)
    return report.text()


__all__ = [
    "BIASES",
    "DEFAULT_ACTION_NOISE",
    "GenerateConfig",
    "GenerateReport",
    "STAGES",
    "ShardResult",
    "generate",
    "generate_cmd",
    "generate_shard",
    "shard_design_list",
    "space_token_maxima",
    "training_motions",
]
