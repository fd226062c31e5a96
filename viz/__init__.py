"""tt.viz: meshcat scenes of robot designs and rollouts, live or as standalone HTML, and
PNG plots for benchmarks.

Modules: `scene` (scene builder and animation), `shapes` (geoms, markers, labels as meshcat
objects), `poses` (body poses from joint trajectories), `camera` (framing),
`episode_file` (episode ``.npz`` files), `html` (offline HTML export), `live` (meshcat
server), `screenshot` (headless Chromium), `plots` (matplotlib PNGs), `cli` (``tt view``).

Names are imported on first use, so ``import tt.viz.plots`` in a benchmark does not load
meshcat or MuJoCo.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "Scene": "tt.viz.scene",
    "SceneError": "tt.viz.scene",
    "SceneOptions": "tt.viz.scene",
    "build_scene": "tt.viz.scene",
    "CameraOptions": "tt.viz.camera",
    "CameraView": "tt.viz.camera",
    "BodyPoses": "tt.viz.poses",
    "PoseError": "tt.viz.poses",
    "body_poses": "tt.viz.poses",
    "EpisodeFileError": "tt.viz.episode_file",
    "EpisodeRecord": "tt.viz.episode_file",
    "load_episode_npz": "tt.viz.episode_file",
    "save_episode_npz": "tt.viz.episode_file",
    "scene_html": "tt.viz.html",
    "write_html": "tt.viz.html",
    "serve_scene": "tt.viz.live",
    "screenshot_html": "tt.viz.screenshot",
    "find_chromium": "tt.viz.screenshot",
    "save_bar_table": "tt.viz.plots",
    "save_scatter": "tt.viz.plots",
    "save_curve": "tt.viz.plots",
    "view_cmd": "tt.viz.cli",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'tt.viz' has no attribute {name!r}")
