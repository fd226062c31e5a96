"""Screenshots of exported scenes with headless Chromium (software WebGL, no GPU needed).

Debian's package is ``chromium`` (``apt-get install -y chromium``). WebGL runs on
SwiftShader through ``--enable-unsafe-swiftshader``; ``--use-gl=swiftshader`` renders a
blank page with current Chromium, so it is not used.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

from tt.kernels.errors import TTError

#: Executable names tried in order.
CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


class ScreenshotError(TTError, RuntimeError):
    """Chromium is missing or failed to write the screenshot."""


def find_chromium() -> str | None:
    """Path of a Chromium executable on PATH, or None."""
    for name in CHROMIUM_NAMES:
        found = shutil.which(name)
        if found:
            return found
    return None


def screenshot_html(
    html: str | Path,
    png: str | Path,
    *,
    width: int = 800,
    height: int = 600,
    time: float | None = None,
    hide_gui: bool = True,
    budget_ms: int = 2000,
    timeout_s: float = 60.0,
) -> Path:
    """Render an exported scene to a PNG of `width` x `height` pixels.

    time: animation time [s] to freeze at (``#t=``); None shows the page as it opens.
    hide_gui: hide meshcat's control panel (``#gui=0``).
    budget_ms: virtual time Chromium lets the page run before the capture [ms].
    """
    exe = find_chromium()
    if exe is None:
        raise ScreenshotError(f"no Chromium found on PATH (tried {', '.join(CHROMIUM_NAMES)}); install: apt-get install -y chromium")
    html = Path(html).resolve()
    if not html.is_file():
        raise FileNotFoundError(f"HTML file {html} does not exist")
    png = Path(png).resolve()
    png.parent.mkdir(parents=True, exist_ok=True)
    png.unlink(missing_ok=True)
    fragment = []
    if time is not None:
        fragment.append(f"t={float(time)!r}")
    if hide_gui:
        fragment.append("gui=0")
    url = html.as_uri() + ("#" + "&".join(fragment) if fragment else "")
    cmd = [
        exe,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--enable-unsafe-swiftshader",
        "--hide-scrollbars",
        f"--window-size={int(width)},{int(height)}",
        f"--virtual-time-budget={int(budget_ms)}",
        f"--screenshot={png}",
        url,
    ]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        raise ScreenshotError(f"Chromium did not finish within {timeout_s} s rendering {html}") from None
    if not png.is_file():
        raise ScreenshotError(f"Chromium wrote no screenshot (exit {proc.returncode}): {proc.stderr[-2000:]}")
    return png
