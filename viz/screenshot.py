"""Screenshots of exported scenes with headless Chromium (software WebGL, no GPU needed).

Debian's package is ``chromium`` (``apt-get install -y chromium``). WebGL runs on
SwiftShader through ``--enable-unsafe-swiftshader``; ``--use-gl=swiftshader`` renders a
blank page with current Chromium, so it is not used.
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

from tt.kernels.errors import TTError
from tt.kernels.files import is_stdout, write_bytes

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
        raise ScreenshotError(
            f"no Chromium found on PATH (tried {', '.join(CHROMIUM_NAMES)}); install: apt-get install -y chromium"
        )
    html = Path(html).resolve()
    if not html.is_file():
        raise FileNotFoundError(f"HTML file {html} does not exist")
    fragment = []
    if time is not None:
        fragment.append(f"t={float(time)!r}")
    if hide_gui:
        fragment.append("gui=0")
    url = html.as_uri() + ("#" + "&".join(fragment) if fragment else "")
    # Chromium writes into a folder of its own; the PNG then replaces `png` in one step
    # (`tt.kernels.files.atomic_write`), so a failed render leaves an earlier file whole.
    with tempfile.TemporaryDirectory(prefix="tt-screenshot-") as tmp:
        shot = Path(tmp) / "screenshot.png"
        cmd = [
            exe,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--enable-unsafe-swiftshader",
            "--hide-scrollbars",
            f"--window-size={int(width)},{int(height)}",
            f"--virtual-time-budget={int(budget_ms)}",
            f"--screenshot={shot}",
            url,
        ]
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise ScreenshotError(f"Chromium did not finish within {timeout_s} s rendering {html}") from None
        if not shot.is_file():
            raise ScreenshotError(f"Chromium wrote no screenshot (exit {proc.returncode}): {proc.stderr[-2000:]}")
        if not is_stdout(png):
            Path(png).parent.mkdir(parents=True, exist_ok=True)
        write_bytes(png, shot.read_bytes())
    return Path(png)
