"""``tt view``: designs or episode files in meshcat, live or as one offline HTML file.

`view_cmd` takes plain arguments so the command-line layer only parses and reports; it
raises `ValueError` subclasses (`ViewError`, `DesignError`, `EpisodeFileError`, ...) and
`FileNotFoundError` with messages meant for the user.
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from tt.kernels.errors import TTError
from tt.sim.designs import DesignError, get_space, load_designs
from tt.sim.motions.base import Motion
from tt.viz.episode_file import EpisodeFileError, load_episode_npz
from tt.viz.html import write_html
from tt.viz.scene import Scene, SceneOptions, build_scene


class ViewError(TTError):
    """A ``tt view`` request that cannot be served; the message says what to change."""


@dataclass
class ViewResult:
    """What `view_cmd` produced.

    scene: the scene shown.
    html: path of the HTML file written, or None.
    png: path of the screenshot written, or None.
    url: URL of the live meshcat viewer, or None.
    visualizer: the live meshcat visualizer (keeps its server alive), or None.
    """

    scene: Scene
    html: Path | None = None
    png: Path | None = None
    url: str | None = None
    visualizer: object | None = None


def load_motion_spec(spec: str, lookup: Callable[[str], Motion] | None = None) -> Motion:
    """A motion by library name (``toss``, ``toss:7``) or file (``.npz``, UMI ``.zarr``),
    through `tt.sim.motions.resolve_motion` unless another `lookup` is given."""
    if lookup is None:
        from tt.sim.motions import resolve_motion as lookup
    motion = lookup(spec)
    if not isinstance(motion, Motion):
        raise ViewError(f"motion {spec!r}: the lookup returned a {type(motion).__name__}, not a Motion")
    return motion


def scene_for_source(source: str, *, motion: Motion | None = None, options: SceneOptions | None = None) -> Scene:
    """The scene for a design file (``designs.json`` or ``designs.json#i``) or an episode
    file (``episode.npz`` or ``episode.npz#w``)."""
    base, sep, index = source.rpartition("#")
    if not sep:
        base, index = source, ""
    if base.endswith(".npz"):
        record = load_episode_npz(base)
        if index:
            try:
                record = record.select([int(index)])
            except ValueError:
                raise ViewError(f"world index {index!r} after '#' is not an integer") from None
        return record.scene(motion=motion, options=options)
    designs = load_designs(source)
    if not designs:
        raise ViewError(f"{base} holds no designs")
    first = int(index) if index else 0
    models, labels = [], []
    for k, d in enumerate(designs):
        label = f"{d.space} #{first + k}"
        try:
            models.append(get_space(d.space).model(d))
        except DesignError:
            raise
        except ValueError as e:  # MuJoCo's compiler
            raise ViewError(f"design {label} of {base}: MuJoCo cannot compile its MJCF: {e}") from None
        labels.append(label)
    return build_scene(models, motions=motion, labels=labels, options=options)


def view_cmd(
    source: str,
    *,
    motion: str | None = None,
    html: str | Path | None = None,
    serve: bool = False,
    png: str | Path | None = None,
    time: float | None = None,
    zmq_url: str | None = None,
    host: str | None = None,
    block: bool = True,
    echo: Callable[[str], None] = print,
    motion_lookup: Callable[[str], Motion] | None = None,
) -> ViewResult:
    """Show designs or an episode: ``tt view SOURCE [--motion M] [--html OUT] [--serve] [--png OUT]``.

    source: ``designs.json`` (all designs side by side), ``designs.json#i`` (one design),
        ``episode.npz`` (every world animated side by side) or ``episode.npz#w`` (one world).
    motion: target motion drawn with the robots: a library name (``toss``, ``toss:7``) or a
        motion file (see `load_motion_spec`); for an episode it replaces the recorded targets.
    html: write one self-contained HTML file (works offline). Default when neither `html`
        nor `serve` is given: ``<source name>.html`` in the current folder.
    serve: start a live meshcat server (or use `zmq_url`'s) and report its URL; with
        `block` wait until interrupted (Ctrl-C) so the server stays up. The server's web
        server listens on `host` (default: the loopback, 127.0.0.1); the server dies with
        this process.
    png: also render the HTML to a PNG with headless Chromium (800 x 600).
    time: animation time [s] the HTML opens paused at, and that `png` shows.
    echo: where messages for the user go (the CLI passes its printer).
    """
    if host is not None and not serve:
        raise ViewError(f"--host {host} is where --serve's viewer listens; give --serve too")
    if host is not None and zmq_url is not None:
        raise ViewError(
            f"--host {host} is for a server tt view starts; the server at {zmq_url} listens where it was started"
        )
    motion_obj = load_motion_spec(motion, motion_lookup) if motion else None
    scene = scene_for_source(source, motion=motion_obj)
    result = ViewResult(scene)
    if html is None and not serve:
        html = Path(Path(source.rpartition("#")[0] or source).stem + ".html")
    if png is not None and html is None:
        raise ViewError("--png renders the exported HTML; give --html too")
    if time is not None and html is None:
        raise ViewError(
            "--time applies to the exported HTML (the time it opens paused at), not --serve's live viewer; "
            "give --html too"
        )
    if time is not None and not 0.0 <= time <= scene.duration + 1e-9:
        raise ViewError(f"--time {time} s is outside the animation, which runs 0..{scene.duration:.2f} s")
    if html is not None:
        result.html = write_html(scene, html, title=f"tt view {source}", paused_at=time)
        extra = f", {scene.duration:.2f} s animation" if scene.frames > 1 else ""
        echo(f"wrote {result.html} ({len(scene.labels)} robot{'s' if len(scene.labels) != 1 else ''}{extra})")
    if png is not None:
        from tt.viz.screenshot import screenshot_html

        result.png = screenshot_html(result.html, png, time=time)
        echo(f"wrote {result.png}")
    if serve:
        from tt.viz.live import DEFAULT_HOST, serve_scene

        result.visualizer = serve_scene(scene, zmq_url=zmq_url, host=DEFAULT_HOST if host is None else host)
        result.url = result.visualizer.url()
        echo(f"meshcat viewer: {result.url}")
        if block:
            _serve_until_stopped(result.visualizer, stop_server=zmq_url is None, echo=echo)
    return result


def _serve_until_stopped(vis, *, stop_server: bool, echo: Callable[[str], None]) -> None:
    """Wait for Ctrl-C, SIGTERM or SIGHUP, then stop the meshcat server this process started
    (left running, it would outlive ``tt view``, orphaned, holding its port)."""
    import signal

    from tt.viz.live import close_visualizer

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    previous = {sig: signal.signal(sig, interrupt) for sig in (signal.SIGTERM, signal.SIGHUP)}
    try:  # from here on a signal stops the server
        echo("serving; press Ctrl-C to stop")
        while True:
            _time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if stop_server:
            close_visualizer(vis)
            echo("stopped the meshcat server")


__all__ = ["ViewError", "ViewResult", "load_motion_spec", "scene_for_source", "view_cmd", "EpisodeFileError"]
