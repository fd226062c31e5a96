"""Tables of validated metrics, as the CLI prints them and the benchmarks write them."""

from __future__ import annotations

import math
from typing import Mapping, Sequence

#: (key, header) of the columns every metrics table shows, in the paper's order.
COLUMNS = (
    ("pos_err", "pos err (cm)"),
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


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, str):
        return v
    if isinstance(v, float) and not math.isfinite(v):
        return "nan"
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"
    return str(v)


def columns_for(reward: str, extra: Sequence[tuple[str, str]] = ()) -> list[tuple[str, str]]:
    cols = list(COLUMNS)
    metric = REWARD_METRIC.get(reward)
    if metric:
        cols.append(metric)
    return cols + list(extra)


def markdown_table(rows: Sequence[Mapping], columns: Sequence[tuple[str, str]], first: tuple[str, str] = ("name", "")) -> str:
    """A GitHub markdown table: one row per mapping, `columns` as (key, header)."""
    cols = [first] + list(columns)
    lines = ["| " + " | ".join(h for _, h in cols) + " |", "|" + "---|" * len(cols)]
    for row in rows:
        lines.append("| " + " | ".join(_fmt(row.get(k)) for k, _ in cols) + " |")
    return "\n".join(lines)


def rich_table(rows: Sequence[Mapping], columns: Sequence[tuple[str, str]], title: str = "", first: tuple[str, str] = ("name", "")):
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
    errors are averaged over episodes that ran at least one step; survival in percent."""
    import numpy as np

    row: dict[str, float] = {}
    for key, value in metrics.items():
        v = np.asarray(value, dtype=np.float64)[index]
        if key == "survival":
            row["survival_pct"] = float(100.0 * np.mean(v))
        else:
            finite = v[np.isfinite(v)]
            row[key] = float(finite.mean()) if finite.size else float("nan")
    return row
