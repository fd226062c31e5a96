"""Live viewing: send a scene to a meshcat server that browsers connect to."""

from __future__ import annotations

import atexit
import contextlib
import io
import logging
import os
import subprocess
import sys
import tempfile

import meshcat

from tt.kernels.errors import TTError
from tt.viz.scene import Scene

log = logging.getLogger(__name__)

#: Where ``tt view --serve``'s web server listens unless told otherwise.
DEFAULT_HOST = "127.0.0.1"


class ServerError(TTError):
    """The meshcat server could not start; the message says why."""


#: Servers this process started and has not stopped; stopped at interpreter exit.
_SERVERS: set[subprocess.Popen] = set()


@atexit.register
def _stop_all() -> None:
    for proc in list(_SERVERS):
        stop_server(proc)


class _Lowered:
    """A command already in lowered form, for meshcat's ``ViewerWindow.send``."""

    __slots__ = ("data",)

    def __init__(self, data: dict) -> None:
        self.data = data

    def lower(self) -> dict:
        return self.data


def open_visualizer(zmq_url: str | None = None, *, host: str = DEFAULT_HOST) -> meshcat.Visualizer:
    """A meshcat visualizer: connect to the server at `zmq_url`, or start a local one whose
    web server listens on `host` (`start_server`)."""
    # meshcat prints its URL on stdout; route it to the log instead.
    out = io.StringIO()
    if zmq_url is not None:
        with contextlib.redirect_stdout(out):
            vis = meshcat.Visualizer(zmq_url=zmq_url)
    else:
        from meshcat.visualizer import ViewerWindow

        proc, url = start_server(host)
        try:
            with contextlib.redirect_stdout(out):
                window = ViewerWindow(zmq_url=url, start_server=False, server_args=[])
        except BaseException:
            stop_server(proc)
            raise
        window.server_proc = proc  # close_visualizer stops it
        vis = meshcat.Visualizer(window=window)
    log.info("meshcat: %s", out.getvalue().strip())
    return vis


def start_server(host: str = DEFAULT_HOST) -> tuple[subprocess.Popen, str]:
    """Start meshcat's server (`tt.viz.meshcat_server`) with its web server on `host`;
    (the process, its command socket's URL). The server exits when this process does,
    however it ends (its parent is watched), and at interpreter exit."""
    _check_host(host)
    with tempfile.TemporaryFile() as errors:  # its complaints, read if it fails to start
        # -P: the current folder is not searched for modules (a file there could shadow one)
        proc = subprocess.Popen(
            [sys.executable, "-P", "-u", "-m", "tt.viz.meshcat_server", "--host", host, "--parent", str(os.getpid())],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=errors,
            start_new_session=True,  # Ctrl-C reaches tt view, which stops the server itself
        )
        _SERVERS.add(proc)
        zmq_url = None
        for raw in proc.stdout:
            line = raw.decode("utf-8", "replace").strip()
            if line.startswith("zmq_url="):
                zmq_url = line.split("=", 1)[1]
            elif line.startswith("web_url=") and zmq_url is not None:
                break
        else:
            proc.wait(timeout=10)
            errors.seek(0)
            why = errors.read().decode("utf-8", "replace").strip().splitlines()
            raise ServerError(
                f"the meshcat server for --serve (--host {host}) exited with code {proc.returncode}: "
                f"{why[-1] if why else 'no message'}"
            )
    proc.stdout.close()
    return proc, zmq_url


def _check_host(host: str) -> None:
    """Refuse an address this machine cannot listen on (meshcat's port search would try a
    thousand ports on it)."""
    import socket

    try:
        family, kind, proto, _, address = socket.getaddrinfo(
            host or None, 0, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )[0]
        with socket.socket(family, kind, proto) as s:
            s.bind(address)
    except OSError as e:
        raise ServerError(f"--host {host}: cannot listen on this address ({e.strerror or e})") from None


def stop_server(proc: subprocess.Popen) -> None:
    """Stop a server `start_server` started and wait for it to exit."""
    _SERVERS.discard(proc)
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)


def send_scene(vis: meshcat.Visualizer, scene: Scene) -> None:
    """Apply the scene's commands to a live visualizer (replacing tt's previous scene)."""
    for cmd in scene.commands:
        vis.window.send(_Lowered(cmd))


def serve_scene(scene: Scene, *, zmq_url: str | None = None, host: str = DEFAULT_HOST) -> meshcat.Visualizer:
    """Show `scene` on a meshcat server (a new local one, its web server on `host`, unless
    `zmq_url` names one); the viewer is at ``vis.url()``. A server started here lives as
    long as this process at most."""
    vis = open_visualizer(zmq_url, host=host)
    send_scene(vis, scene)
    return vis


def close_visualizer(vis: meshcat.Visualizer) -> None:
    """Stop the meshcat server `vis` started (if it started one) and wait for it to exit."""
    proc = getattr(vis.window, "server_proc", None)
    if proc is not None:
        stop_server(proc)
