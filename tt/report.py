"""Tables of validated metrics, as the CLI prints them and the benchmarks write them."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Mapping, Sequence

#: (key, header) of the columns every metrics table shows, in the paper's order.
COLUMNS = (
    ("pos_err", "pos err (cm)"),
    ("pos_err_p95", "p95 pos err (cm)"),
    ("within_2cm_pct", "within 2 cm (%)"),
    ("orn_err", "orn err (deg)"),
    ("survival_pct", "survival (%)"),
    ("reward", "reward"),
)

#: The reward-specific metric each reward reports (paper appendix).
REWARD_METRIC = {
    "tracking": None,
    "tracking_torque": ("torque", "torque (N m)"),
    "tracking_velocity": ("velocity", "velocity (rad/s)"),
    "tracking_size": ("size", "size (m)"),
    "tracking_weight": ("mass", "mass (kg)"),
}

#: Columns shown beside a reward's metric: the max joint speed beside the mean velocity (the
#: paper's ALOHA result reports the max).
BESIDE_METRIC = {"velocity": (("max_joint_speed", "max joint speed (rad/s)"),)}


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, str):
        return v
    if isinstance(v, float) and not math.isfinite(v):
        return "-"
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"
    return str(v)


def columns_for(reward: str, extra: Sequence[tuple[str, str]] = ()) -> list[tuple[str, str]]:
    """The columns of a metrics table for `reward` (tt's name or an alias), then `extra`."""
    from tt.kernels.errors import TTError
    from tt.sim.rewards import reward_name

    try:
        reward = reward_name(reward)
    except TTError:
        pass  # no reward-specific column
    cols = list(COLUMNS)
    metric = REWARD_METRIC.get(reward)
    if metric:
        cols.append(metric)
        cols.extend(BESIDE_METRIC.get(metric[0], ()))
    return cols + list(extra)


def markdown_table(
    rows: Sequence[Mapping], columns: Sequence[tuple[str, str]], first: tuple[str, str] = ("name", "")
) -> str:
    """A GitHub markdown table: one row per mapping, `columns` as (key, header)."""
    cols = [first] + list(columns)
    lines = ["| " + " | ".join(h for _, h in cols) + " |", "|" + "---|" * len(cols)]
    for row in rows:
        lines.append("| " + " | ".join(_fmt(row.get(k)) for k, _ in cols) + " |")
    return "\n".join(lines)


def rich_table(
    rows: Sequence[Mapping], columns: Sequence[tuple[str, str]], title: str = "", first: tuple[str, str] = ("name", "")
):
    """The same table for the terminal (rich)."""
    from rich.table import Table

    table = Table(title=title)
    for k, h in [first] + list(columns):
        table.add_column(h, justify="left" if k == first[0] else "right")
    for row in rows:
        table.add_row(*[_fmt(row.get(k)) for k, _ in [first] + list(columns)])
    return table


def summary_row(metrics: Mapping, index: int | slice = slice(None)) -> dict[str, float]:
    """Aggregate (D, M) metric arrays of an `Evaluation` over motions (and the selected designs):
    errors are averaged over episodes that ran at least one step; survival and the share within
    2 cm in percent; the max joint speed, a max within each episode, is averaged over episodes
    too."""
    import numpy as np

    from tt.sim.rewards import PERCENT_METRICS

    row: dict[str, float] = {}
    for key, value in metrics.items():
        v = np.asarray(value, dtype=np.float64)[index]
        if key in PERCENT_METRICS:
            row[PERCENT_METRICS[key]] = float(100.0 * np.mean(v))
        else:
            finite = v[np.isfinite(v)]
            row[key] = float(finite.mean()) if finite.size else float("nan")
    return row


def ratio_ci(a, b, *, samples: int = 10_000, seed: int = 0) -> tuple[float, float, float]:
    """mean(a) / mean(b) of paired runs, with its 95 % percentile-bootstrap interval
    (runs resampled with replacement, pairs kept): (ratio, low, high)."""
    import numpy as np

    from tt.kernels.errors import TTError

    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 1 or a.size == 0:
        raise TTError(f"ratio_ci needs two equal-length 1-D samples, got shapes {a.shape} and {b.shape}")
    idx = np.random.default_rng(seed).integers(0, a.size, size=(samples, a.size))
    boot = a[idx].mean(axis=1) / b[idx].mean(axis=1)
    low, high = np.percentile(boot, [2.5, 97.5])
    return float(a.mean() / b.mean()), float(low), float(high)


def mean_ci(values) -> tuple[float, float]:
    """Mean and half-width of the 95 % Student-t confidence interval of the finite values
    (None skipped); NaN half-width for one value, NaN both for none."""
    import numpy as np
    from scipy import stats

    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return float("nan"), float("nan")
    if v.size == 1:
        return float(v[0]), float("nan")
    return float(v.mean()), float(stats.t.ppf(0.975, v.size - 1) * v.std(ddof=1) / math.sqrt(v.size))


def plot_method_bars(
    settings: Mapping[str, Sequence[Mapping]], path, order: Sequence[str] | None = None, space: str = "ViperX"
) -> None:
    """One column per setting: validated reward (top) and optimize time (bottom, log scale) per
    reward and method, mean with 95 % CI. Records carry method, reward_name, reward, seconds;
    `order` fixes the methods' order (default: first appearance)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, axes = plt.subplots(2, len(settings), figsize=(6.5 * len(settings), 7), squeeze=False)
    for col, (name, records) in enumerate(settings.items()):
        rewards = list(dict.fromkeys(r["reward_name"] for r in records))
        present = list(dict.fromkeys(r["method"] for r in records))
        labels = [m for m in order if m in present] if order else present
        width = 0.8 / max(len(labels), 1)
        for row, key in enumerate(("reward", "seconds")):
            ax = axes[row][col]
            for j, label in enumerate(labels):
                ms = [
                    mean_ci([r[key] for r in records if r["method"] == label and r["reward_name"] == rw])
                    for rw in rewards
                ]
                x = np.arange(len(rewards)) + (j - (len(labels) - 1) / 2) * width
                ax.bar(
                    x,
                    [m if math.isfinite(m) else 0.0 for m, _ in ms],
                    width,
                    yerr=[h if math.isfinite(h) else 0.0 for _, h in ms],
                    capsize=3,
                    label=label,
                )
            ax.set_xticks(np.arange(len(rewards)), rewards, rotation=15)
            ax.set_ylabel("validated reward" if key == "reward" else "optimize time (s)")
            if key == "seconds":
                ax.set_yscale("log")
            ax.set_title(f"{space}, {name}")
            ax.legend(fontsize=7)
    fig.tight_layout()
    from tt.kernels.files import atomic_write

    with atomic_write(path) as f:
        fig.savefig(f, dpi=110, format=Path(path).suffix.lstrip(".").lower() or "png")
    plt.close(fig)
