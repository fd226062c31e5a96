"""tt.viz: scenes against MuJoCo's kinematics, episode files, HTML export rendered in
headless Chromium, the live server, the CLI entry and the PNG plots.

References: `mujoco.mj_kinematics` (geom_xpos / geom_xmat / site_xpos / xpos / xquat) for
every pose the scene tree encodes; the pinhole camera model for where the robot must
appear in a screenshot; the inputs themselves for plots and files.
"""

from __future__ import annotations

import base64
import json
import re
import urllib.request
from concurrent.futures import ThreadPoolExecutor

import mujoco
import numpy as np
import pytest
import torch
import umsgpack

from tt.kernels.rotations import quat_to_mat
from tt.sim.designs import DesignError, get_space, save_designs
from tt.sim.episode import Episode
from tt.sim.motions.base import Motion
from tt.viz.camera import CameraOptions, CameraView, frame_points
from tt.viz.cli import ViewError, view_cmd
from tt.viz.episode_file import EpisodeFileError, EpisodeRecord, load_episode_npz, save_episode_npz
from tt.viz.html import scene_html, viewer_js_path, write_html
from tt.viz.poses import PoseError, body_poses
from tt.viz.scene import ROOT, SceneError, build_scene
from tt.viz.screenshot import find_chromium, screenshot_html
from tt.viz.shapes import capsule_mesh, rgba_to_hex

# Every primitive type, a material colour, a free-floating body and a site.
PRIMITIVES_XML = """
<mujoco>
  <asset><material name="gold" rgba="0.9 0.7 0.1 1"/></asset>
  <worldbody>
    <geom name="floor" type="plane" size="0 0 0.1" rgba="0.3 0.3 0.3 1"/>
    <body name="base" pos="0.1 0.2 0.3" quat="0.9238795 0 0 0.3826834">
      <joint name="j0" type="hinge" axis="0 0 1"/>
      <geom name="ball" type="sphere" size="0.05" pos="0 0 0.05" rgba="1 0 0 1"/>
      <geom name="cap" type="capsule" fromto="0 0 0 0.3 0 0.1" size="0.03" rgba="0 1 0 1"/>
      <body name="link" pos="0.3 0 0.1">
        <joint name="j1" type="hinge" axis="0 1 0"/>
        <geom name="cyl" type="cylinder" fromto="0 0 0 0 0.2 0.2" size="0.02" rgba="0 0 1 0.5"/>
        <geom name="egg" type="ellipsoid" size="0.03 0.04 0.05" pos="0.1 0 0" euler="0.3 0.2 0.1" material="gold"/>
        <site name="ee_0" pos="0 0.2 0.2" size="0.01"/>
      </body>
    </body>
    <body name="crate" pos="0.5 -0.3 0.2">
      <freejoint/>
      <geom name="box" type="box" size="0.05 0.06 0.07" rgba="0.9 0.6 0.1 1"/>
    </body>
  </worldbody>
</mujoco>
"""


def _primitives():
    model = mujoco.MjModel.from_xml_string(PRIMITIVES_XML)
    q = model.qpos0.copy()
    q[0], q[1] = 0.7, -0.4
    q[2:5] = [0.4, -0.2, 0.5]
    q[5:9] = np.array([0.8, 0.2, -0.3, 0.4]) / np.linalg.norm([0.8, 0.2, -0.3, 0.4])
    return model, q


def _tree(scene):
    """Local transforms and objects by path, as the viewer would hold them."""
    local, objects = {}, {}
    for c in scene.commands:
        if c["type"] == "set_transform":
            local[c["path"]] = np.array(c["matrix"]).reshape(4, 4).T
        elif c["type"] == "set_object":
            objects[c["path"]] = c["object"]
    return local, objects


def _world(scene, local, path):
    """World transform of a scene-tree path, undoing the framing shift."""
    parts = path.strip("/").split("/")
    m = np.eye(4)
    for k in range(1, len(parts) + 1):
        m = m @ local.get("/" + "/".join(parts[:k]), np.eye(4))
    shift = np.eye(4)
    shift[:3, 3] = scene.view.center
    return shift @ m


def _find(objects, suffix):
    hits = [p for p in objects if p.endswith(suffix)]
    assert len(hits) == 1, (suffix, hits)
    return hits[0]


def _ext_floats(ext) -> np.ndarray:
    assert ext.type == 0x17
    return np.frombuffer(ext.data, dtype=np.float32)


# ---------------------------------------------------------------- scene vs MuJoCo
def test_geoms_are_drawn_at_mujoco_poses_with_their_sizes_and_colours():
    model, q = _primitives()
    data = mujoco.MjData(model)
    data.qpos[:] = q
    mujoco.mj_kinematics(model, data)
    scene = build_scene([model], qpos=[q])
    local, objects = _tree(scene)
    drawn = 0
    for g in range(model.ngeom):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g)
        path = _find(objects, f"_{name}")
        obj = objects[path]
        world = _world(scene, local, path)
        geometry = obj["geometries"][0]
        size = model.geom_size[g]
        gtype = model.geom_type[g]
        rot = data.geom_xmat[g].reshape(3, 3)
        if gtype == mujoco.mjtGeom.mjGEOM_PLANE:
            # Drawn as a 2 mm slab whose top face is the plane.
            np.testing.assert_allclose(world[:3, 3], data.geom_xpos[g] - 0.001 * rot[:, 2], atol=1e-12)
        else:
            np.testing.assert_allclose(world[:3, 3], data.geom_xpos[g], atol=1e-12)
        if gtype == mujoco.mjtGeom.mjGEOM_CYLINDER:
            # three.js cylinders run along their y axis, MuJoCo's along z.
            np.testing.assert_allclose(world[:3, 1], rot[:, 2], atol=1e-12)
            assert geometry["type"] == "CylinderGeometry"
            assert geometry["height"] == pytest.approx(2 * size[1])
            assert geometry["radiusTop"] == geometry["radiusBottom"] == pytest.approx(size[0])
        else:
            np.testing.assert_allclose(world[:3, :3], rot, atol=1e-12)
        if gtype == mujoco.mjtGeom.mjGEOM_BOX:
            assert [geometry["width"], geometry["height"], geometry["depth"]] == pytest.approx(2 * size)
        elif gtype == mujoco.mjtGeom.mjGEOM_SPHERE:
            assert geometry["radius"] == pytest.approx(size[0])
        elif gtype == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
            assert np.diag(np.array(obj["object"]["matrix"]).reshape(4, 4))[:3] == pytest.approx(size)
        elif gtype == mujoco.mjtGeom.mjGEOM_CAPSULE:
            verts = (
                np.frombuffer(geometry["data"]["attributes"]["position"]["array"].data, np.float32).reshape(-1, 3).T
            )  # interleaved xyz
            r, h = size[0], size[1]
            np.testing.assert_allclose(verts.min(1), [-r, -r, -h - r], atol=1e-6)
            np.testing.assert_allclose(verts.max(1), [r, r, h + r], atol=1e-6)
        elif gtype == mujoco.mjtGeom.mjGEOM_PLANE:
            assert geometry["depth"] == pytest.approx(0.002)
        rgba = model.mat_rgba[model.geom_matid[g]] if name == "egg" else model.geom_rgba[g]
        material = obj["materials"][0]
        assert material["color"] == rgba_to_hex(rgba)
        assert material["opacity"] == pytest.approx(rgba[3])
        assert material["transparent"] == (rgba[3] < 1)
        drawn += 1
    assert drawn == model.ngeom == 6


def test_end_effector_site_is_drawn_at_mujoco_site_pose():
    model, q = _primitives()
    data = mujoco.MjData(model)
    data.qpos[:] = q
    mujoco.mj_kinematics(model, data)
    scene = build_scene([model], qpos=[q])
    local, objects = _tree(scene)
    path = _find(objects, "_ee_0")
    world = _world(scene, local, path)
    np.testing.assert_allclose(world[:3, 3], data.site_xpos[0], atol=1e-12)
    np.testing.assert_allclose(world[:3, :3], data.site_xmat[0].reshape(3, 3), atol=1e-12)
    assert f"{path}/axes" in objects


def test_animation_tracks_follow_mj_kinematics_and_targets():
    model, q0 = _primitives()
    frames = 7
    qs = np.repeat(q0[None], frames, axis=0)
    qs[:, 0] = np.linspace(0.0, 1.5, frames)
    qs[:, 2] = np.linspace(0.4, 0.9, frames)
    t = np.arange(frames)
    pos = np.stack([0.3 + 0.01 * t, 0.1 * np.sin(t), 0.2 + 0 * t], -1)[:, None]
    quat = np.stack([np.cos(0.1 * t), 0 * t, 0 * t, np.sin(0.1 * t)], -1)[:, None]
    motion = Motion("wiggle", pos, quat)
    scene = build_scene([model], qpos=[qs], motions=motion, dt=0.02)
    assert scene.frames == frames and scene.duration == pytest.approx(0.12)
    anim = [c for c in scene.commands if c["type"] == "set_animation"]
    assert len(anim) == 1
    clips = {a["path"]: a["clip"] for a in anim[0]["animations"]}
    data = mujoco.MjData(model)
    ref_pos = np.zeros((frames, model.nbody, 3))
    ref_quat = np.zeros((frames, model.nbody, 4))
    for k in range(frames):
        data.qpos[:] = qs[k]
        mujoco.mj_kinematics(model, data)
        ref_pos[k], ref_quat[k] = data.xpos, data.xquat
    for b in range(1, model.nbody):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b)
        path = _find(clips, f"/{b:02d}_{name}")
        clip = clips[path]
        assert clip["fps"] == pytest.approx(50.0)
        tracks = {tr["name"]: tr for tr in clip["tracks"]}
        np.testing.assert_array_equal(_ext_floats(tracks[".position"]["times"]), np.arange(frames))
        np.testing.assert_allclose(
            _ext_floats(tracks[".position"]["values"]).reshape(frames, 3), ref_pos[:, b], atol=1e-6
        )
        xyzw = _ext_floats(tracks[".quaternion"]["values"]).reshape(frames, 4)
        np.testing.assert_allclose(xyzw[:, [3, 0, 1, 2]], ref_quat[:, b], atol=1e-6)
    target = clips[_find(clips, "/target/frame_0")]
    tracks = {tr["name"]: tr for tr in target["tracks"]}
    np.testing.assert_allclose(_ext_floats(tracks[".position"]["values"]).reshape(frames, 3), pos[:, 0], atol=1e-6)
    local, objects = _tree(scene)
    line = objects[_find(objects, "/target/path_0")]
    pts = np.frombuffer(line["geometries"][0]["data"]["attributes"]["position"]["array"].data, np.float32)
    np.testing.assert_allclose(pts.reshape(frames, 3), pos[:, 0], atol=1e-6)


def test_body_poses_checks_qpos_width_and_values():
    model, q = _primitives()
    with pytest.raises(PoseError, match=r"nq = 9"):
        body_poses(model, np.zeros((3, 8)))
    bad = np.repeat(q[None], 3, axis=0)
    bad[1, 0] = np.nan
    with pytest.raises(PoseError, match="frame 1"):
        body_poses(model, bad)


def test_quat_to_mat_matches_mujoco():
    rng = np.random.default_rng(0)
    quats = rng.normal(size=(20, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    ref = np.zeros(9)
    for qt, m in zip(quats, quat_to_mat(quats)):
        mujoco.mju_quat2Mat(ref, qt)
        np.testing.assert_allclose(m, ref.reshape(3, 3), atol=1e-12)


def test_capsule_mesh_is_closed_and_outward():
    v, f = capsule_mesh(0.03, 0.1, segments=16, rings=4)
    # Closed surface: every edge is shared by exactly two faces, in opposite directions.
    edges = {}
    for a, b, c in f:
        for e in ((a, b), (b, c), (c, a)):
            edges[e] = edges.get(e, 0) + 1
    assert all(n == 1 for n in edges.values()) and all((b, a) in edges for a, b in edges)
    # Outward winding: the signed volume (divergence theorem) is the capsule's volume.
    tri = v[f].astype(np.float64)
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0
    exact = np.pi * 0.03**2 * 0.2 + 4.0 / 3.0 * np.pi * 0.03**3
    assert volume == pytest.approx(exact, rel=0.08)  # a 16-gon lathe under-fills the circle


# ---------------------------------------------------------------- camera and layout
def test_projection_is_a_pinhole_with_z_up():
    view = CameraView(center=np.array([1.0, 2.0, 3.0]), eye=np.array([2.0, 0.0, 0.0]), fov_deg=60.0)
    px = view.project(np.array([[1.0, 2.0, 3.0], [1.0, 2.0, 3.5], [1.0, 2.5, 3.0], [4.0, 2.0, 3.0]]), 800, 600)
    focal = 300.0 / np.tan(np.radians(30.0))
    np.testing.assert_allclose(px[0], [400.0, 300.0])
    np.testing.assert_allclose(px[1], [400.0, 300.0 - focal * 0.5 / 2.0])  # up on screen
    # Looking along -x, +y is to the right.
    np.testing.assert_allclose(px[2], [400.0 + focal * 0.5 / 2.0, 300.0])
    assert np.all(np.isnan(px[3]))  # behind the eye


def test_framing_fits_every_point_in_the_window():
    rng = np.random.default_rng(1)
    pts = rng.uniform([-0.5, -1.0, 0.0], [1.5, 0.3, 0.9], size=(200, 3))
    opts = CameraOptions(azimuth_deg=-50.0, elevation_deg=30.0, fov_deg=40.0, aspect=4 / 3, margin=1.1)
    view = frame_points(pts, np.zeros(200), opts)
    px = view.project(pts, 800, 600)
    assert np.all((px[:, 0] > 0) & (px[:, 0] < 800) & (px[:, 1] > 0) & (px[:, 1] < 600))
    # Tight: the content spans most of the window in at least one direction.
    span = (px.max(0) - px.min(0)) / [800, 600]
    assert span.max() > 0.75
    with pytest.raises(ValueError, match="elevation_deg"):
        CameraOptions(elevation_deg=90.0)


def test_grid_cells_do_not_overlap_and_labels_are_kept():
    space = get_space("viperx")
    designs = [space.nominal()] + space.sample(3, seed=4)
    models = [space.model(d) for d in designs]
    labels = ["Random", "CMA-ES", "Zeroth", "Self-Guidance"]
    scene = build_scene(models, labels=labels)
    assert scene.labels == tuple(labels)
    local, objects = _tree(scene)
    boxes = []
    for i, m in enumerate(models):
        cell = f"{ROOT}/robot_{i:02d}"
        assert f"{cell}/label" in objects
        pts = np.array([_world(scene, local, p)[:3, 3] for p in objects if p.startswith(f"{cell}/bodies/")])
        boxes.append((pts.min(0), pts.max(0)))
    for i in range(4):
        for j in range(i + 1, 4):
            (lo_i, hi_i), (lo_j, hi_j) = boxes[i], boxes[j]
            overlap = np.all(lo_i[:2] < hi_j[:2]) and np.all(lo_j[:2] < hi_i[:2])
            assert not overlap, (i, j)


def test_scene_input_errors_name_the_argument():
    model, q = _primitives()
    with pytest.raises(SceneError, match="labels has 2 entries"):
        build_scene([model], labels=["a", "b"])
    with pytest.raises(SceneError, match="models is empty"):
        build_scene([])
    two_arms = Motion("two", np.zeros((3, 2, 3)), np.tile([1.0, 0, 0, 0], (3, 2, 1)))
    with pytest.raises(SceneError, match="2 end effectors.*1 end-effector site"):
        build_scene([model], motions=two_arms)
    with pytest.raises(PoseError, match="robot 0"):
        build_scene([model], qpos=[np.zeros((4, 3))])


# ---------------------------------------------------------------- episode files
def _episode(models, frames=30, seed=0):
    """An Episode over `models` (same topology), with smooth joint motion."""
    rng = np.random.default_rng(seed)
    w = len(models)
    nq, nv, nu = models[0].nq, models[0].nv, models[0].nu
    t = np.arange(frames) * 0.02
    qpos = 0.5 * np.sin(t[None, :, None] * rng.uniform(1, 3, size=(w, 1, nq)))
    tp = rng.normal(size=(w, frames, 1, 3))
    tq = rng.normal(size=(w, frames, 1, 4))
    tq /= np.linalg.norm(tq, axis=-1, keepdims=True)
    z = lambda *s: torch.zeros(*s, dtype=torch.float32)  # noqa: E731
    alive = torch.ones(w, frames, dtype=torch.bool)
    alive[0, -5:] = False
    return Episode(
        qpos=torch.tensor(qpos, dtype=torch.float32),
        qvel=z(w, frames, nv),
        ctrl=z(w, frames, nu),
        action=z(w, frames, nu),
        act_force=z(w, frames, nu),
        act_vel=z(w, frames, nu),
        ee_pos=torch.tensor(tp, dtype=torch.float32),
        ee_quat=torch.tensor(tq, dtype=torch.float32),
        target_pos=torch.tensor(tp, dtype=torch.float32),
        target_quat=torch.tensor(tq, dtype=torch.float32),
        alive=alive,
        fallen=torch.zeros(w, frames, dtype=torch.bool),
        design_index=torch.arange(w),
        motion_index=torch.zeros(w, dtype=torch.long),
        dt=0.02,
    )


def _same_dof_designs(n, dof="6"):
    space = get_space("viperx")
    return [d for d in space.sample(60, seed=3) if space.to_dict(d)["discrete"]["dof"] == dof][:n]


def test_episode_file_round_trip(tmp_path):
    space = get_space("viperx")
    designs = _same_dof_designs(2)
    models = [space.model(d) for d in designs]
    ep = _episode(models)
    path = save_episode_npz(tmp_path / "run.npz", ep, designs, labels=["a", "b"], motion_name="wave")
    assert path == tmp_path / "run.npz" and path.is_file()
    rec = load_episode_npz(path)
    assert rec.designs == tuple(designs)
    assert rec.labels == ("a", "b") and rec.motion_name == "wave" and rec.dt == pytest.approx(0.02)
    np.testing.assert_array_equal(rec.qpos, ep.qpos.numpy())
    np.testing.assert_array_equal(rec.alive, ep.alive.numpy())
    np.testing.assert_array_equal(rec.target_pos, ep.target_pos.numpy())
    assert list(rec.nbody) == [m.nbody for m in models]
    scene = rec.scene()
    assert scene.frames == 30 and scene.labels == ("a", "b")
    # Concatenating (e.g. winners of different methods) pads shorter episodes and widens qpos.
    other = EpisodeRecord.from_episode(
        _episode([space.model(_same_dof_designs(1, "7")[0])], frames=10), _same_dof_designs(1, "7"), labels=["c"]
    )
    both = EpisodeRecord.concat([rec, other])
    assert both.worlds == 3 and both.steps == 30 and both.qpos.shape[2] == 7
    np.testing.assert_array_equal(both.world_qpos(2)[10:], np.repeat(other.qpos[0, -1:], 20, axis=0))
    assert not both.alive[2, 10:].any()
    assert both.select([-1]).labels == ("c",)


def test_episode_whose_body_count_does_not_match_its_design_is_refused(tmp_path):
    space = get_space("viperx")
    designs = _same_dof_designs(1)
    rec = EpisodeRecord.from_episode(_episode([space.model(designs[0])]), designs)
    bad = EpisodeRecord(
        rec.designs,
        rec.qpos,
        rec.nq,
        rec.nbody + 1,
        rec.alive,
        rec.target_pos,
        rec.target_quat,
        rec.labels,
        rec.motion_name,
        rec.dt,
    )
    path = save_episode_npz(tmp_path / "bad.npz", bad)
    with pytest.raises(EpisodeFileError, match=r"poses for 9 bodies .* model with 8 bodies"):
        view_cmd(str(path), html=tmp_path / "x.html", echo=lambda s: None)
    assert not (tmp_path / "x.html").exists()


def test_episode_qpos_must_fit_its_designs():
    space = get_space("viperx")
    six = _same_dof_designs(1, "6")
    seven = _same_dof_designs(1, "7")
    ep = _episode([space.model(six[0])])
    with pytest.raises(EpisodeFileError, match="6 columns .* nq = 7"):
        EpisodeRecord.from_episode(ep, seven)
    # Wider qpos is zero padding from a batch of mixed DoF: the world uses its first nq columns.
    rec = EpisodeRecord.from_episode(_episode([space.model(seven[0])]), six)
    assert rec.nq[0] == 6 and rec.world_qpos(0).shape == (30, 6)


def test_bad_episode_files_are_named(tmp_path):
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    with pytest.raises(EpisodeFileError, match="junk.npz is not an .npz archive"):
        load_episode_npz(junk)
    partial = tmp_path / "partial.npz"
    np.savez(partial, qpos=np.zeros((1, 2, 3)))
    with pytest.raises(EpisodeFileError, match="missing keys"):
        load_episode_npz(partial)
    with pytest.raises(FileNotFoundError):
        load_episode_npz(tmp_path / "absent.npz")


# ---------------------------------------------------------------- CLI entry
def test_view_design_file_writes_html_and_rejects_bad_designs(tmp_path):
    space = get_space("viperx")
    designs = space.sample(3, seed=2)
    save_designs(designs, tmp_path / "d.json")
    lines = []
    res = view_cmd(f"{tmp_path / 'd.json'}#1", html=tmp_path / "one.html", echo=lines.append)
    assert res.scene.labels == ("viperx #1",) and res.html.is_file()
    assert "wrote" in lines[0]
    res = view_cmd(str(tmp_path / "d.json"), html=tmp_path / "all.html", echo=lines.append)
    assert len(res.scene.labels) == 3
    # A design that does not load: an option outside the space.
    data = json.loads((tmp_path / "d.json").read_text())
    data["designs"][0]["discrete"]["mount"] = "ceiling"
    (tmp_path / "bad.json").write_text(json.dumps(data))
    with pytest.raises(DesignError, match="'mount' = 'ceiling'"):
        view_cmd(str(tmp_path / "bad.json"), html=tmp_path / "bad.html", echo=lines.append)
    with pytest.raises(FileNotFoundError):
        view_cmd(str(tmp_path / "none.json"), html=tmp_path / "none.html", echo=lines.append)
    with pytest.raises(ViewError, match="outside the animation"):
        view_cmd(str(tmp_path / "d.json"), html=tmp_path / "t.html", time=2.0, echo=lines.append)


def test_view_with_library_motion_and_motion_file(tmp_path):
    from tt.sim.motions import get_motion, save_npz

    space = get_space("viperx")
    save_designs([space.nominal()], tmp_path / "d.json")
    toss = get_motion("toss")
    res = view_cmd(str(tmp_path / "d.json"), motion="toss", html=tmp_path / "m.html", echo=lambda s: None)
    assert res.scene.frames == toss.steps  # the target frame moves along the motion
    local, objects = _tree(res.scene)
    line = objects[_find(objects, "/target/path_0")]
    pts = np.frombuffer(line["geometries"][0]["data"]["attributes"]["position"]["array"].data, np.float32)
    np.testing.assert_allclose(pts.reshape(-1, 3), toss.pos[:, 0], atol=1e-6)
    save_npz(toss, tmp_path / "toss.npz")
    res = view_cmd(
        str(tmp_path / "d.json"), motion=str(tmp_path / "toss.npz"), html=tmp_path / "f.html", echo=lambda s: None
    )
    assert res.scene.frames == toss.steps


# ---------------------------------------------------------------- HTML and Chromium
def test_html_is_self_contained_and_carries_the_scene():
    model, q = _primitives()
    scene = build_scene([model], qpos=[np.stack([q, q])])
    page = scene_html(scene, paused_at=0.5)
    assert viewer_js_path().read_text(encoding="utf-8") in page
    # Nothing is fetched: no external scripts, styles, images or URLs.
    assert not re.search(r"""(src|href)\s*=""", page.replace(viewer_js_path().read_text(encoding="utf-8"), ""))
    urls = set(re.findall(r"https?://[^\s\"'<>)]+", page))
    assert urls <= {"https://github.com/rdeits/meshcat", "http://www.w3.org/1999/xhtml"}, urls
    blobs = json.loads(re.search(r"var commands = (\[.*?\]);", page, re.S).group(1))
    decoded = [umsgpack.unpackb(base64.b64decode(b)) for b in blobs]
    assert [c["type"] for c in decoded] == [c["type"] for c in scene.commands]
    assert decoded[-1]["type"] == "set_animation"
    assert ": 0.5;" in page  # opens paused at 0.5 s unless the URL says otherwise


def _unit_sphere(n=400):
    """Quasi-uniform points on the unit sphere (Fibonacci lattice), (n, 3)."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = np.pi * (1 + 5**0.5) * k
    return np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], -1)


def _robot_surface(model, qpos):
    """Points on the surface of every geom and along the end-effector axes at joint positions
    `qpos`, placed with MuJoCo's kinematics, (K, 3) [m]; and the geom centres, (G, 3) [m]."""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    sphere = _unit_sphere()
    ring = np.stack(
        [np.cos(np.linspace(0, 2 * np.pi, 96)), np.sin(np.linspace(0, 2 * np.pi, 96)), 0 * np.arange(96)], -1
    )
    pts = []
    for g in range(model.ngeom):
        size = model.geom_size[g]
        gtype = int(model.geom_type[g])
        if gtype == int(mujoco.mjtGeom.mjGEOM_CAPSULE):
            local = np.vstack([size[0] * sphere + [0, 0, z] for z in (-size[1], size[1])])
        elif gtype == int(mujoco.mjtGeom.mjGEOM_CYLINDER):
            local = np.vstack([size[0] * ring + [0, 0, z] for z in (-size[1], size[1])])
        elif gtype == int(mujoco.mjtGeom.mjGEOM_BOX):
            local = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T * size
        elif gtype == int(mujoco.mjtGeom.mjGEOM_ELLIPSOID):
            local = sphere * size
        else:
            local = sphere * size[0]
        pts.append(data.geom_xpos[g] + local @ data.geom_xmat[g].reshape(3, 3).T)
    for s in range(model.nsite):  # the end-effector axes, 6 cm long
        pts.append(data.site_xpos[s] + 0.06 * data.site_xmat[s].reshape(3, 3).T)
    return np.vstack(pts), data.geom_xpos.copy()


def _bbox_px(view, surface, offset):
    """Pixel box (col0, row0, col1, row1) of the projected surface points in an 800 x 600 window."""
    px = view.project(surface[0] + offset, 800, 600)
    return np.concatenate([px.min(0), px.max(0)])


def _drawn_bbox(mask):
    rows, cols = np.nonzero(mask)
    return np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], dtype=float)


def _center_pixels(view, surface, offset):
    """(row, col) pixels where the geom centres project."""
    px = np.round(view.project(surface[1] + offset, 800, 600)).astype(int)
    return px[:, ::-1]


def _diff_mask(a, b):
    return np.abs(a.astype(int) - b.astype(int)).sum(-1) > 30


def _inside(mask, box, pad=4):
    rows, cols = np.nonzero(mask)
    ok = (cols >= box[0] - pad) & (cols <= box[2] + pad) & (rows >= box[1] - pad) & (rows <= box[3] + pad)
    return ok.mean()


@pytest.mark.skipif(
    find_chromium() is None, reason="headless Chromium not installed (Debian: apt-get install -y chromium)"
)
def test_exported_html_renders_the_robot_and_its_animation_in_chromium(tmp_path):
    from PIL import Image

    space = get_space("viperx")
    model = space.model(space.nominal())
    frames = 51
    qs = np.zeros((frames, model.nq))
    qs[:, 0] = np.linspace(0.0, 1.3, frames)  # waist swings the arm round
    qs[:, 1] = np.linspace(0.0, 0.6, frames)  # shoulder leans forward
    scene = build_scene([model], qpos=[qs], labels=["nominal"])
    robot = f"{ROOT}/robot_00/bodies"
    empty = build_scene([model], qpos=[qs], labels=["nominal"])
    # The same scene, framing and label without the robot's bodies: the background to beat.
    empty.commands = [
        c for c in empty.commands if not c.get("path", "").startswith(robot) and c["type"] != "set_animation"
    ]
    write_html(scene, tmp_path / "scene.html")
    write_html(empty, tmp_path / "empty.html")
    jobs = [("empty.html", "empty.png", None), ("scene.html", "t0.png", 0.0), ("scene.html", "t1.png", 1.0)]
    with ThreadPoolExecutor(len(jobs)) as pool:
        list(pool.map(lambda j: screenshot_html(tmp_path / j[0], tmp_path / j[1], time=j[2]), jobs))
    empty_px, t0, t1 = (np.asarray(Image.open(tmp_path / j[1]).convert("RGB")) for j in jobs)
    assert t0.shape == (600, 800, 3)

    offset = scene.cell_offsets[0]
    first, last = _robot_surface(model, qs[0]), _robot_surface(model, qs[-1])
    for shot, surface in ((t0, first), (t1, last)):
        drawn = _diff_mask(shot, empty_px)
        box = _bbox_px(scene.view, surface, offset)
        # The robot is drawn where MuJoCo's kinematics and the pinhole camera put it: every
        # geom centre is covered and the drawn pixels span the predicted box, to within
        # antialiasing (a pixel or two) and the sampling of the geom surfaces.
        rows, cols = _center_pixels(scene.view, surface, offset).T
        assert drawn[rows, cols].all()
        np.testing.assert_allclose(_drawn_bbox(drawn), box, atol=3.0)
    # The later screenshot shows the later pose: frame 0's geom centres are not all covered.
    rows, cols = _center_pixels(scene.view, first, offset).T
    assert not _diff_mask(t1, empty_px)[rows, cols].all()
    moved = _diff_mask(t0, t1)
    assert moved.sum() > 2000
    b0, b1 = _bbox_px(scene.view, first, offset), _bbox_px(scene.view, last, offset)
    union = np.concatenate([np.minimum(b0[:2], b1[:2]), np.maximum(b0[2:], b1[2:])])
    assert _inside(moved, union) > 0.999


# ---------------------------------------------------------------- live server
def test_serve_starts_a_live_server_that_holds_the_scene(tmp_path):
    from tt.viz.live import close_visualizer

    space = get_space("viperx")
    save_designs([space.nominal()], tmp_path / "d.json")
    lines = []
    res = view_cmd(str(tmp_path / "d.json"), motion="toss", serve=True, block=False, echo=lines.append)
    vis = res.visualizer
    try:
        assert res.url and any(res.url in line for line in lines) and res.html is None
        page = urllib.request.urlopen(res.url, timeout=10).read().decode()
        assert "MeshCat" in page
        # The server keeps every command except deletions to replay to new browsers.
        stored = vis.static_html().count('fetch("data:')
        assert stored == sum(c["type"] != "delete" for c in res.scene.commands)
    finally:
        close_visualizer(vis)
    assert vis.window.server_proc.poll() is not None


def test_serve_listens_where_asked_and_host_needs_serve(tmp_path, tt_cli):
    """The web server on --host (every interface here), the command socket on the loopback
    still; --host without --serve, or an address not of this machine, is refused."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from listening import listening

    from tt.viz.live import close_visualizer

    save_designs([get_space("viperx").nominal()], tmp_path / "d.json")
    res = view_cmd(str(tmp_path / "d.json"), serve=True, host="0.0.0.0", block=False, echo=lambda _: None)
    try:
        addresses = listening(res.visualizer.window.server_proc.pid)
        web = int(res.url.split(":")[2].split("/")[0])
        assert ("0.0.0.0", web) in addresses and [h for h, p in addresses if p != web] == ["127.0.0.1"], addresses
    finally:
        close_visualizer(res.visualizer)
    code, text = tt_cli(["view", str(tmp_path / "d.json"), "--host", "0.0.0.0", "--html", str(tmp_path / "v.html")])
    assert code == 2 and "--host" in text and "--serve" in text, text
    code, text = tt_cli(
        ["view", str(tmp_path / "d.json"), "--serve", "--host", "198.51.100.77"]
    )  # TEST-NET-2: no machine's own
    assert code == 2 and "--host 198.51.100.77" in text and "cannot listen" in text, text


# ---------------------------------------------------------------- plots
def test_bar_table_draws_values_and_intervals(tmp_path):
    from tt.viz.plots import PlotError, bar_table_figure, save_bar_table

    cats = ["ViperX", "bimanual"]
    series = {"Random": [19.4, 30.0], "CMA-ES": [5.0, 8.0]}
    ci = {"Random": ([17.0, 25.0], [22.0, 33.0])}
    fig = bar_table_figure(cats, series, ci=ci, title="Tracking error", ylabel="position error [cm]")
    ax = fig.axes[0]
    heights = sorted(round(p.get_height(), 6) for p in ax.patches)
    assert heights == sorted([19.4, 30.0, 5.0, 8.0])
    segs = [s for c in ax.collections for s in c.get_segments()]
    spans = sorted((round(s[0][1], 6), round(s[1][1], 6)) for s in segs)
    assert spans == [(17.0, 22.0), (25.0, 33.0)]
    assert ax.get_ylabel() == "position error [cm]" and ax.get_title() == "Tracking error"
    out = save_bar_table(tmp_path / "bars.png", cats, series, ci=ci, title="t", ylabel="y [cm]", dpi=100)
    from PIL import Image

    assert Image.open(out).size == (700, 420)
    with pytest.raises(PlotError, match="excludes the value"):
        bar_table_figure(cats, series, ci={"Random": ([20.0, 25.0], [22.0, 33.0])}, title="t", ylabel="y")
    with pytest.raises(PlotError, match="3 values; expected 2"):
        bar_table_figure(cats, {"a": [1, 2, 3]}, title="t", ylabel="y")
    with pytest.raises(PlotError, match="ylabel"):
        bar_table_figure(cats, series, title="t", ylabel="")


def test_scatter_and_curve(tmp_path):
    from tt.viz.plots import PlotError, curve_figure, save_curve, save_scatter, scatter_figure

    fig = scatter_figure(
        [1.0, 2.0, 3.0],
        [4.0, 5.0, 6.0],
        groups=["a", "a", "b"],
        annotations=["x", "y", "z"],
        yci=([3.5, 4.5, 5.0], [4.5, 5.5, 7.0]),
        title="s",
        xlabel="time [s]",
        ylabel="error [cm]",
    )
    ax = fig.axes[0]
    assert [t.get_text() for t in ax.texts] == ["x", "y", "z"]
    assert sorted(t.get_text() for t in ax.get_legend().get_texts()) == ["a", "b"]
    assert save_scatter(tmp_path / "s.png", [1, 2], [3, 4], title="s", xlabel="x [m]", ylabel="y [m]").is_file()
    x = np.linspace(0, 1, 11)
    fig = curve_figure(
        x, {"loss": x**2}, ci={"loss": (x**2 - 0.1, x**2 + 0.2)}, title="c", xlabel="step", ylabel="loss"
    )
    ax = fig.axes[0]
    np.testing.assert_allclose(ax.lines[0].get_ydata(), x**2)
    band = ax.collections[0].get_paths()[0].vertices
    assert band[:, 1].min() == pytest.approx(-0.1) and band[:, 1].max() == pytest.approx(1.2)
    assert save_curve(tmp_path / "c.png", x, {"a": x}, title="c", xlabel="step", ylabel="loss").is_file()
    with pytest.raises(PlotError, match=r"\.png"):
        save_curve(tmp_path / "c.jpg", x, {"a": x}, title="c", xlabel="step", ylabel="loss")
