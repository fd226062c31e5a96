"""Live viewing: send a scene to a meshcat server that browsers connect to."""

from __future__ import annotations

import contextlib
import io
import logging
import subprocess

import meshcat

from tt.viz.scene import Scene

log = logging.getLogger(__name__)


class _Lowered:
    """A command already in lowered form, for meshcat's ``ViewerWindow.send``."""

    __slots__ = ("data",)

    def __init__(self, data: dict) -> None:
        self.data = data

    def lower(self) -> dict:
        return self.data


def open_visualizer(zmq_url: str | None = None) -> meshcat.Visualizer:
    """A meshcat visualizer: connect to the server at `zmq_url`, or start a local one."""
    # meshcat prints its URL on stdout; route it to the log instead.
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        vis = meshcat.Visualizer(zmq_url=zmq_url)
    log.info("meshcat: %s", out.getvalue().strip())
    return vis


def send_scene(vis: meshcat.Visualizer, scene: Scene) -> None:
    """Apply the scene's commands to a live visualizer (replacing tt's previous scene)."""
    for cmd in scene.commands:
        vis.window.send(_Lowered(cmd))


def serve_scene(scene: Scene, *, zmq_url: str | None = None) -> meshcat.Visualizer:
    """Show `scene` on a meshcat server (a new local one unless `zmq_url` names one);
    the viewer is at ``vis.url()``. The server lives as long as the returned visualizer's
    process."""
    vis = open_visualizer(zmq_url)
    send_scene(vis, scene)
    return vis


def close_visualizer(vis: meshcat.Visualizer) -> None:
    """Stop the meshcat server `vis` started (if it started one) and wait for it to exit."""
    proc = getattr(vis.window, "server_proc", None)
    if proc is not None and proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)
