"""What a RoboToken dataset holds: `dataset_info` (counts, token maxima, normalisation
statistics, episode summaries; JSON-ready) and `info_text`, the text `tt dataset info`
prints. The reward histogram as a PNG is `tt.viz.plots.save_reward_histogram`; the CLI
command that puts them together is in `tt.cli`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tt.tokens.schema import SCHEMA
from tt.tokens.store import TokenStore


def dataset_info(path: str | Path, *, verify: str = "size") -> tuple[dict, np.ndarray]:
    """Summary of the dataset at `path`: (info, rewards).

    info: JSON-ready dict: path, format, schema_version, tt_version, space, config,
    complete, shards (and shards_expected, damaged), designs, episodes (kept, and
    episodes_generated, dropped by reason), steps, bytes on disk, maxima (tokens per robot /
    per step), per-episode summaries (n, mean, std, min, p50, max) of length, reward,
    pos_err, orn_err and survival, and the normalisation statistics (low, high per type).
    rewards: the (E,) reward of every kept episode, float.
    verify: how `TokenStore` checks the shards ("size" or "full"). Raises `DatasetError`
    for a folder that is not a dataset.
    """
    store = TokenStore(path, verify=verify)
    table = store.episode_table()
    attrs = store.attrs
    generated = sum(int(r.attrs.get("generated", r.episodes)) for r in store.readers)
    dropped: dict[str, int] = {}
    for r in store.readers:
        for k, v in r.attrs.get("dropped", {}).items():
            dropped[k] = dropped.get(k, 0) + int(v)
    size = sum(p.stat().st_size for p in Path(path).rglob("*") if p.is_file())
    reward = table.get("reward", np.zeros(0))
    out = {
        "path": str(path),
        "format": attrs["format"],
        "schema_version": attrs["schema_version"],
        "tt_version": attrs.get("tt_version"),
        "space": attrs.get("space"),
        "config": attrs.get("config", {}),
        "complete": bool(attrs.get("complete", False)),
        "shards": len(store.readers),
        "shards_expected": attrs.get("config", {}).get("shards"),
        "damaged": store.damaged,
        "designs": sum(r.attrs["designs"] for r in store.readers),
        "episodes": store.episodes,
        "episodes_generated": generated,
        "dropped": dropped,
        "steps": sum(int(r.attrs["steps"]) for r in store.readers),
        "bytes": size,
        "maxima": store.maxima,
    }
    if len(table.get("length", [])):
        out["length"] = _summary(table["length"].astype(np.float64))
    for k in ("reward", "pos_err", "orn_err", "survival"):
        if k in table and len(table[k]):
            out[k] = _summary(table[k].astype(np.float64))
    if store.readers:
        norm = store.normalizer()
        out["statistics"] = {n: {"low": norm.low[n].tolist(), "high": norm.high[n].tolist()} for n in norm.low}
    return out, reward


def info_text(info: dict, rewards: np.ndarray) -> str:
    """The text of ``tt dataset info``: `dataset_info`'s summary and a text histogram of the
    episode rewards."""
    cfg = info["config"]
    lines = [
        f"{info['path']}: {info['format']}, RoboToken schema v{info['schema_version']}, tt {info['tt_version']}",
        f"space {info['space']}; seed {cfg.get('seed')}; bias {cfg.get('bias') or 'none'}; "
        f"{cfg.get('episodes_per_design')} episodes per design; min {cfg.get('min_steps')} steps",
        f"shards {info['shards']}/{info['shards_expected']}"
        + ("" if info["complete"] else " (incomplete: run `tt generate` again)")
        + (f"; damaged: {sorted(info['damaged'])}" if info["damaged"] else ""),
        f"designs {info['designs']:,}; episodes {info['episodes']:,} kept of {info['episodes_generated']:,} generated"
        + "".join(f"; dropped {v:,} {k}" for k, v in sorted(info["dropped"].items()) if v),
        f"steps {info['steps']:,}; size on disk {format_bytes(info['bytes'])}",
    ]
    if "length" in info:
        ln = info["length"]
        lines.append(
            f"episode length [steps]: mean {ln['mean']:.1f}, min {ln['min']:.0f}, median {ln['p50']:.0f}, max "
            f"{ln['max']:.0f}"
        )
    for k, unit in (("pos_err", "cm"), ("orn_err", "deg"), ("survival", "")):
        if k in info and info[k].get("n"):
            lines.append(f"{k} [{unit or '1'}]: mean {info[k]['mean']:.3f}, median {info[k]['p50']:.3f}")
    lines.append("token maxima (per robot | per step):")
    lines.append("  " + ", ".join(f"{k} {v}" for k, v in info["maxima"].items()))
    if "statistics" in info:
        lines.append("normalisation ranges (low .. high of each attribute, first value):")
        for name, st in info["statistics"].items():
            t = SCHEMA[name]
            parts = []
            for a in t.attributes:
                sl = t.slice(a.name)
                parts.append(f"{a.name} {st['low'][sl.start]:.3g}..{st['high'][sl.start]:.3g}")
            lines.append(f"  {name}: " + ", ".join(parts))
    lines.append("episode rewards (tracking):")
    lines += _text_histogram(rewards)
    return "\n".join(lines)


def format_bytes(n: float) -> str:
    """A byte count in B, KiB, MiB, GiB or TiB, one decimal."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n:.1f} TiB"


def _summary(x: np.ndarray) -> dict[str, float]:
    x = x[np.isfinite(x)]
    if not len(x):
        return {"n": 0}
    return {
        "n": int(len(x)),
        "mean": float(x.mean()),
        "std": float(x.std()),
        "min": float(x.min()),
        "p50": float(np.median(x)),
        "max": float(x.max()),
    }


def _text_histogram(x: np.ndarray, bins: int = 12, width: int = 40) -> list[str]:
    x = x[np.isfinite(x)]
    if not len(x):
        return ["  (no episodes)"]
    counts, edges = np.histogram(x, bins=bins)
    top = max(int(counts.max()), 1)
    return [
        f"  {edges[i]:9.2f} .. {edges[i + 1]:9.2f} | {'#' * int(round(width * c / top)):<{width}} {c}"
        for i, c in enumerate(counts)
    ]


__all__ = ["dataset_info", "format_bytes", "info_text"]
