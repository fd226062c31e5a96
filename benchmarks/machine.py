"""Machine, date and versions for the header of every benchmark table."""

from __future__ import annotations

import datetime
import os
import platform
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path


def _cpu_name() -> str:
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_header(device: str = "cpu") -> str:
    """Markdown lines: date, CPU (cores), device, Python and package versions."""
    pkgs = []
    for name in ("torch", "warp-lang", "mujoco", "mujoco-warp", "newton", "mink", "numpy"):
        try:
            pkgs.append(f"{name} {version(name)}")
        except PackageNotFoundError:
            pass
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return (
        f"- date: {now}\n"
        f"- machine: {_cpu_name()}, {os.cpu_count()} cores, {platform.system()} {platform.machine()}\n"
        f"- device: {device}\n"
        f"- python {platform.python_version()}; " + ", ".join(pkgs) + "\n"
    )


def load_line() -> str:
    """The 1, 5 and 15 min load averages, as "a, b, c"."""
    return ", ".join(f"{v:.1f}" for v in os.getloadavg())


def write_report(path, lines: list[str]) -> Path:
    """Write a results file's lines (its folder made if missing); returns its path."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    return out
