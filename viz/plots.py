"""PNG plots for benchmarks, reports and datasets: grouped bars, scatter plots, curves and
reward histograms (`tt dataset info --plot`), each with
a title, axis labels (put units in them: ``"position error [cm]"``) and confidence intervals.

Figures are built with matplotlib's object API (no pyplot, no global state), so they
render headless and in parallel. Each ``save_*`` has a ``*_figure`` twin that returns the
`matplotlib.figure.Figure` for callers (and tests) that want to inspect or extend it.

Confidence intervals are given as bounds: ``{"series": (low, high)}`` with `low` and
`high` shaped like the values, the form bootstrap and t intervals come in.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

from tt.kernels.errors import TTError


class PlotError(TTError):
    """Plot inputs of mismatched shapes, missing labels or intervals that exclude their value."""


_Interval = tuple[Sequence[float], Sequence[float]]


def _require_text(**fields: str) -> None:
    for name, value in fields.items():
        if not isinstance(value, str) or not value.strip():
            raise PlotError(f"{name} must be a non-empty string (with units where the axis has them), got {value!r}")


def _values(name: str, values, n: int | None = None) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64).reshape(-1)
    if n is not None and arr.shape[0] != n:
        raise PlotError(f"{name} has {arr.shape[0]} values; expected {n}")
    return arr


def _error_distances(name: str, values: np.ndarray, interval: _Interval | None) -> np.ndarray | None:
    """(2, N) distances below and above `values` for matplotlib from CI bounds."""
    if interval is None:
        return None
    if len(interval) != 2:
        raise PlotError(f"interval of {name!r} must be (low, high) bounds, got {len(interval)} entries")
    low = _values(f"low bound of {name!r}", interval[0], values.shape[0])
    high = _values(f"high bound of {name!r}", interval[1], values.shape[0])
    ok = np.isnan(values) | ((low <= values + 1e-12 * np.abs(values)) & (values <= high + 1e-12 * np.abs(values)))
    if not np.all(ok):
        k = int(np.argmin(ok))
        raise PlotError(
            f"interval of {name!r} at index {k} is [{low[k]}, {high[k]}], which excludes the value {values[k]}"
        )
    return np.stack([values - low, high - values])


def _finish(fig: Figure, path: str | Path, dpi: int) -> Path:
    from tt.kernels.files import atomic_write, is_stdout

    path = Path(path)
    if path.suffix.lower() != ".png" and not is_stdout(path):
        raise PlotError(f"path {path} must end in .png")
    if not is_stdout(path):
        path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as f:
        fig.savefig(f, dpi=dpi, format="png")
    return path


# ---------------------------------------------------------------- bars
def bar_table_figure(
    categories: Sequence[str],
    series: Mapping[str, Sequence[float]],
    *,
    title: str,
    ylabel: str,
    xlabel: str = "",
    ci: Mapping[str, _Interval] | None = None,
    value_format: str = "{:.3g}",
    log_y: bool = False,
    size: tuple[float, float] = (7.0, 4.2),
) -> Figure:
    """Grouped bars: one group per category, one bar per series, each bar labelled with its
    value and, where `ci` has the series, an error bar spanning its interval."""
    _require_text(title=title, ylabel=ylabel)
    categories = [str(c) for c in categories]
    if not categories or not series:
        raise PlotError("categories and series must be non-empty")
    ci = dict(ci or {})
    unknown = set(ci) - set(series)
    if unknown:
        raise PlotError(f"ci has series {sorted(unknown)} that are not in series {list(series)}")
    fig = Figure(figsize=size, layout="constrained")
    ax = fig.add_subplot()
    n_series = len(series)
    width = 0.8 / n_series
    x = np.arange(len(categories))
    for k, (name, vals) in enumerate(series.items()):
        v = _values(f"series {name!r}", vals, len(categories))
        err = _error_distances(name, v, ci.get(name))
        bars = ax.bar(x + (k - (n_series - 1) / 2) * width, v, width, yerr=err, capsize=3, label=str(name))
        ax.bar_label(bars, labels=[value_format.format(val) for val in v], padding=2, fontsize=8)
    ax.set_xticks(x, categories)
    ax.set_title(title)
    ax.set_ylabel(ylabel)
    if xlabel:
        ax.set_xlabel(xlabel)
    if log_y:
        ax.set_yscale("log")
    ax.margins(y=0.12)
    if n_series > 1:
        ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    return fig


def save_bar_table(
    path: str | Path, categories: Sequence[str], series: Mapping[str, Sequence[float]], *, dpi: int = 150, **kwargs
) -> Path:
    """Write `bar_table_figure` (same arguments) to the PNG at `path`; returns the path."""
    return _finish(bar_table_figure(categories, series, **kwargs), path, dpi)


# ---------------------------------------------------------------- scatter
def scatter_figure(
    x: Sequence[float],
    y: Sequence[float],
    *,
    title: str,
    xlabel: str,
    ylabel: str,
    groups: Sequence[str] | None = None,
    annotations: Sequence[str] | None = None,
    xci: _Interval | None = None,
    yci: _Interval | None = None,
    log_x: bool = False,
    log_y: bool = False,
    size: tuple[float, float] = (6.0, 4.5),
) -> Figure:
    """Points (x, y), coloured and listed in the legend by `groups`, optionally annotated
    with text, with interval bars from `xci` / `yci` bounds."""
    _require_text(title=title, xlabel=xlabel, ylabel=ylabel)
    xv = _values("x", x)
    yv = _values("y", y, xv.shape[0])
    xerr = _error_distances("x", xv, xci)
    yerr = _error_distances("y", yv, yci)
    group_of = ["" for _ in xv] if groups is None else [str(g) for g in groups]
    if len(group_of) != xv.shape[0]:
        raise PlotError(f"groups has {len(group_of)} entries; expected {xv.shape[0]}")
    fig = Figure(figsize=size, layout="constrained")
    ax = fig.add_subplot()
    for g in dict.fromkeys(group_of):
        m = np.array([gg == g for gg in group_of])
        ax.errorbar(
            xv[m],
            yv[m],
            xerr=None if xerr is None else xerr[:, m],
            yerr=None if yerr is None else yerr[:, m],
            fmt="o",
            capsize=3,
            label=g or None,
        )
    if annotations is not None:
        if len(annotations) != xv.shape[0]:
            raise PlotError(f"annotations has {len(annotations)} entries; expected {xv.shape[0]}")
        for xi, yi, text in zip(xv, yv, annotations):
            ax.annotate(str(text), (xi, yi), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.set_title(title)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if log_x:
        ax.set_xscale("log")
    if log_y:
        ax.set_yscale("log")
    if groups is not None:
        ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    return fig


def save_scatter(path: str | Path, x: Sequence[float], y: Sequence[float], *, dpi: int = 150, **kwargs) -> Path:
    """Write `scatter_figure` (same arguments) to the PNG at `path`; returns the path."""
    return _finish(scatter_figure(x, y, **kwargs), path, dpi)


# ---------------------------------------------------------------- curves
def curve_figure(
    x: Sequence[float],
    curves: Mapping[str, Sequence[float]],
    *,
    title: str,
    xlabel: str,
    ylabel: str,
    ci: Mapping[str, _Interval] | None = None,
    log_x: bool = False,
    log_y: bool = False,
    size: tuple[float, float] = (6.5, 4.2),
) -> Figure:
    """Curves over a shared `x` (e.g. loss over training steps, error over time), each with a
    shaded band between its `ci` bounds where given."""
    _require_text(title=title, xlabel=xlabel, ylabel=ylabel)
    xv = _values("x", x)
    if not curves:
        raise PlotError("curves must be non-empty")
    ci = dict(ci or {})
    unknown = set(ci) - set(curves)
    if unknown:
        raise PlotError(f"ci has curves {sorted(unknown)} that are not in curves {list(curves)}")
    fig = Figure(figsize=size, layout="constrained")
    ax = fig.add_subplot()
    for name, vals in curves.items():
        v = _values(f"curve {name!r}", vals, xv.shape[0])
        (line,) = ax.plot(xv, v, label=str(name))
        if name in ci:
            err = _error_distances(name, v, ci[name])
            ax.fill_between(xv, v - err[0], v + err[1], color=line.get_color(), alpha=0.2, linewidth=0)
    ax.set_title(title)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if log_x:
        ax.set_xscale("log")
    if log_y:
        ax.set_yscale("log")
    if len(curves) > 1:
        ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    return fig


def save_curve(
    path: str | Path, x: Sequence[float], curves: Mapping[str, Sequence[float]], *, dpi: int = 150, **kwargs
) -> Path:
    """Write `curve_figure` (same arguments) to the PNG at `path`; returns the path."""
    return _finish(curve_figure(x, curves, **kwargs), path, dpi)


# ---------------------------------------------------------------- histograms
def reward_histogram_figure(
    rewards: Sequence[float],
    *,
    title: str,
    bins: int = 50,
    xlabel: str = "episode reward (tracking, sum over steps)",
    size: tuple[float, float] = (6.0, 3.5),
) -> Figure:
    """Histogram of per-episode rewards (non-finite ones left out; the title gives n)."""
    _require_text(title=title, xlabel=xlabel)
    x = np.asarray(rewards, dtype=np.float64).reshape(-1)
    x = x[np.isfinite(x)]
    fig = Figure(figsize=size, layout="constrained")
    ax = fig.add_subplot()
    ax.hist(x, bins=bins, color="#4477aa")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("episodes")
    ax.set_title(f"{title} (n = {len(x)})")
    ax.grid(alpha=0.3)
    return fig


def save_reward_histogram(path: str | Path, rewards: Sequence[float], *, dpi: int = 120, **kwargs) -> Path:
    """Write `reward_histogram_figure` (same arguments) to the PNG at `path`; returns the path."""
    return _finish(reward_histogram_figure(rewards, **kwargs), path, dpi)
