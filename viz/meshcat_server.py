"""meshcat's server as ``tt view --serve`` runs it: ``python -m tt.viz.meshcat_server``.

meshcat 0.3.2's own server (``python -m meshcat.servers.zmqserver``) binds its command socket
to the loopback but its web server to every interface, and has no flag to change that; and
a server child outlives a parent that dies by SIGKILL. This one is meshcat's bridge with

* the web server on ``--host`` (the loopback by default) and the command socket on the
  loopback always (only the local tt process sends scenes);
* an end when its parent ends: ``--parent PID`` is watched (the process exits once it has
  another parent, as an orphan does), so no signal or crash of ``tt view`` leaves it
  listening.

It prints ``zmq_url=...`` and ``web_url=...`` on stdout, as meshcat's does, then stops
writing to stdout (its parent does not read past those lines).
"""

from __future__ import annotations

import argparse
import os
import socket
import sys
import threading
import time

from meshcat.servers.zmqserver import ZMQWebSocketBridge

#: Seconds between checks that the parent still lives.
PARENT_POLL_S = 0.2


class LocalBridge(ZMQWebSocketBridge):
    """meshcat's ZMQ-to-websocket bridge with its web server bound to `web_host` and its
    command socket to 127.0.0.1."""

    def __init__(self, web_host: str = "127.0.0.1") -> None:
        self._web_host = web_host
        super().__init__(host="127.0.0.1")  # the command socket's address (and, by meshcat, the URL's)
        self.web_url = f"http://{url_host(web_host)}:{self.fileserver_port}/static/"

    def make_app(self):
        app = super().make_app()
        listen = app.listen

        def listen_on_host(port, **kwargs):
            return listen(port, address=self._web_host, **kwargs)

        app.listen = listen_on_host  # meshcat's port search calls app.listen(port)
        return app


def url_host(host: str) -> str:
    """The host part of the viewer's URL for a listening address (a wildcard address is
    reached through this machine's name)."""
    if host in ("", "0.0.0.0", "::"):
        return socket.gethostname()
    return f"[{host}]" if ":" in host else host


def exit_with_parent(parent: int) -> None:
    """Exit this process as soon as `parent` is no longer its parent (it died: the process
    was re-parented to init or a subreaper)."""
    if os.getppid() != parent:
        os._exit(0)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_POLL_S)
        os._exit(0)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="meshcat's server for tt view --serve")
    parser.add_argument("--host", default="127.0.0.1", help="address the web server listens on")
    parser.add_argument("--parent", type=int, default=None, help="exit when this process is no longer the parent")
    args = parser.parse_args(argv)
    if args.parent is not None:
        exit_with_parent(args.parent)
    bridge = LocalBridge(args.host)
    sys.stdout.write(f"zmq_url={bridge.zmq_url}\nweb_url={bridge.web_url}\n")
    sys.stdout.flush()
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)  # the parent reads no further: a full pipe must never block the server
    try:
        bridge.run()
    except KeyboardInterrupt:
        pass


if __name__ == "__main__":
    main()
