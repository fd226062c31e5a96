"""Standalone HTML export of a scene: one file, meshcat's viewer inlined, no network.

The page decodes the scene's msgpack commands and hands them to the viewer. The URL
fragment controls the animation, so one file serves live viewing and reproducible stills:

``scene.html#t=1.5``   pause the animation at 1.5 s (a still for screenshots and papers);
``scene.html#gui=0``   hide meshcat's control panel; combine with ``&``: ``#t=1.5&gui=0``.
"""

from __future__ import annotations

import base64
import json
from pathlib import Path

import meshcat

from tt.kernels.errors import TTError
from tt.viz.scene import Scene


class ViewerAssetError(TTError, RuntimeError):
    """meshcat's bundled viewer JavaScript is missing from its installation."""


def viewer_js_path() -> Path:
    """Path of meshcat's bundled viewer (three.js, msgpack and the viewer in one file)."""
    path = Path(meshcat.__file__).parent / "viewer" / "dist" / "main.min.js"
    if not path.is_file():
        raise ViewerAssetError(f"meshcat's viewer bundle is missing: {path} (reinstall meshcat)")
    return path


# The viewer bundle is MIT-licensed (meshcat, three.js and friends); their notices travel
# with the file in a comment.
_PAGE = """<!DOCTYPE html>
<html>
<head>
<meta charset="utf-8">
<title>{title}</title>
<style>
body {{ margin: 0; }}
#meshcat-pane {{ width: 100vw; height: 100vh; overflow: hidden; }}
</style>
</head>
<body>
<div id="meshcat-pane"></div>
<!-- MeshCat viewer (MIT licence, https://github.com/rdeits/meshcat), bundled with three.js (MIT) -->
<script>
{viewer_js}
</script>
<script>
(function () {{
  var viewer = new MeshCat.Viewer(document.getElementById("meshcat-pane"));
  window.viewer = viewer;
  var commands = {commands};
  for (var k = 0; k < commands.length; k++) {{
    var raw = atob(commands[k]);
    var bytes = new Uint8Array(raw.length);
    for (var i = 0; i < raw.length; i++) bytes[i] = raw.charCodeAt(i);
    viewer.handle_command_bytearray(bytes);
  }}
  var params = new URLSearchParams(window.location.hash.slice(1));
  var t = params.has("t") ? parseFloat(params.get("t")) : {paused_at};
  var animator = viewer.animator;
  if (t !== null && isFinite(t) && animator.actions.length > 0) {{
    // Actions must be running for the mixer to apply them; pausing right away freezes the clock.
    animator.play();
    animator.pause();
    animator.seek(t);
    animator.display_progress(t);
  }}
  if (params.get("gui") === "0") viewer.gui.domElement.style.display = "none";
}})();
</script>
</body>
</html>
"""


def scene_html(scene: Scene, *, title: str = "tt viewer", paused_at: float | None = None) -> str:
    """The scene as one self-contained HTML page.

    paused_at: animation time [s] to open paused at; None plays from the start. A ``#t=``
    fragment in the URL overrides it.
    """
    js = viewer_js_path().read_text(encoding="utf-8")
    if "</script" in js.lower():
        raise ViewerAssetError("meshcat's viewer bundle contains '</script' and cannot be inlined safely")
    blobs = [base64.b64encode(b).decode("ascii") for b in scene.pack()]
    return _PAGE.format(
        title=_escape(title),
        viewer_js=js,
        commands=json.dumps(blobs),
        paused_at="null" if paused_at is None else repr(float(paused_at)),
    )


def write_html(scene: Scene, path: str | Path, *, title: str = "tt viewer", paused_at: float | None = None) -> Path:
    """Write `scene_html` to `path` (parent folders created); returns the path."""
    from tt.kernels.files import is_stdout, write_text

    path = Path(path)
    if not is_stdout(path):
        path.parent.mkdir(parents=True, exist_ok=True)
    write_text(path, scene_html(scene, title=title, paused_at=paused_at))
    return path


def _escape(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
