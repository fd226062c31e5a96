"""Meshcat objects for MuJoCo's primitive geoms, end-effector markers, target paths and labels.

Every function returns an object in the lowered form of a meshcat ``set_object`` command
(three.js JSON object format), so the same object can go to a live meshcat server or into a
standalone HTML file.

three.js draws cylinders along their y axis while MuJoCo's cylinders and capsules run
along z; `GeomVisual.local` folds the quarter turn that reconciles the two into the
geom's transform, so the scene tree holds plain rigid transforms.
"""

from __future__ import annotations

import io
import logging
from dataclasses import dataclass

import meshcat.geometry as mg
import mujoco
import numpy as np

from tt.viz.poses import pose_matrix, rotation_x

log = logging.getLogger(__name__)

#: MuJoCo's default geom colour; a geom that keeps it takes its material's colour instead.
_DEFAULT_RGBA = np.array([0.5, 0.5, 0.5, 1.0], dtype=np.float32)

_CYLINDER_TO_Z = rotation_x(np.pi / 2)  # three.js y axis -> MuJoCo z axis


@dataclass(frozen=True)
class GeomVisual:
    """One drawable geom of a model.

    geom_id, body_id: indices into the model's geoms and bodies.
    name: path-safe name, unique within the model.
    object: lowered meshcat object (three.js JSON).
    local: transform from the body frame to the drawn object's frame, (4, 4).
    center: geom centre in the body frame [m], (3,).
    radius: radius of a sphere about `center` that holds the geom [m] (0 for planes).
    """

    geom_id: int
    body_id: int
    name: str
    object: dict
    local: np.ndarray
    center: np.ndarray
    radius: float


def path_name(index: int, name: str, kind: str) -> str:
    """A scene-tree path element for an indexed MuJoCo element: ``03_wrist`` or ``03_geom``."""
    safe = "".join(c if c.isalnum() or c in "_-" else "_" for c in name) or kind
    return f"{index:02d}_{safe}"


def rgba_to_hex(rgba) -> int:
    """0xRRGGBB integer of an (r, g, b[, a]) colour with components in [0, 1]."""
    r, g, b = (int(round(255 * min(max(float(c), 0.0), 1.0))) for c in list(rgba)[:3])
    return (r << 16) | (g << 8) | b


def geom_rgba(model: mujoco.MjModel, geom_id: int) -> np.ndarray:
    """The colour MuJoCo draws a geom with: its own rgba, or its material's if it kept the default."""
    rgba = np.asarray(model.geom_rgba[geom_id], dtype=np.float32)
    matid = int(model.geom_matid[geom_id])
    if matid >= 0 and np.allclose(rgba, _DEFAULT_RGBA):
        return np.asarray(model.mat_rgba[matid], dtype=np.float32)
    return rgba


def _material(rgba) -> mg.MeshPhongMaterial:
    return mg.MeshPhongMaterial(color=rgba_to_hex(rgba), opacity=float(rgba[3]), shininess=40)


def capsule_mesh(
    radius: float, half_length: float, segments: int = 24, rings: int = 6
) -> tuple[np.ndarray, np.ndarray]:
    """Triangle mesh of a capsule along z: a cylinder of `half_length` [m] capped by hemispheres
    of `radius` [m]. Returns vertices (V, 3) and faces (F, 3), counter-clockwise seen from outside."""
    # Profile from the bottom pole to the top pole, excluding the poles: (ring radius, z).
    angles = np.linspace(-np.pi / 2, 0.0, rings + 1)[1:]
    bottom = [(radius * np.cos(a), -half_length + radius * np.sin(a)) for a in angles]
    top = [(r, -z) for r, z in reversed(bottom)]
    profile = np.array(bottom + top)
    phi = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring_xyz = np.stack(
        [profile[:, :1] * np.cos(phi), profile[:, :1] * np.sin(phi), np.repeat(profile[:, 1:], segments, axis=1)], -1
    ).reshape(-1, 3)
    south = len(ring_xyz)
    north = south + 1
    vertices = np.vstack([ring_xyz, [[0.0, 0.0, -half_length - radius], [0.0, 0.0, half_length + radius]]])
    faces = []
    nxt = (np.arange(segments) + 1) % segments
    for k in range(len(profile) - 1):
        a = k * segments + np.arange(segments)
        b = k * segments + nxt
        c = (k + 1) * segments + nxt
        d = (k + 1) * segments + np.arange(segments)
        faces += list(np.stack([a, b, c], 1)) + list(np.stack([a, c, d], 1))
    faces += list(np.stack([np.full(segments, south), nxt, np.arange(segments)], 1))
    last = (len(profile) - 1) * segments
    faces += list(np.stack([np.full(segments, north), last + np.arange(segments), last + nxt], 1))
    return vertices.astype(np.float32), np.asarray(faces, dtype=np.uint32)


def geom_visuals(
    model: mujoco.MjModel, *, groups: tuple[int, ...] = (0, 1, 2), plane_extent: float = 1.0
) -> list[GeomVisual]:
    """Drawable primitive geoms of a model: planes, spheres, capsules, ellipsoids, cylinders, boxes.

    groups: geom groups to draw (MuJoCo's viewer shows 0, 1 and 2 by default).
    plane_extent: half size [m] drawn for a plane whose size is 0 (infinite).
    Geoms with alpha 0, outside `groups`, or of non-primitive types (mesh, height field,
    SDF) are skipped; the last are logged, since tt's design spaces never produce them.
    """
    out: list[GeomVisual] = []
    skipped = 0
    for g in range(model.ngeom):
        if int(model.geom_group[g]) not in groups:
            continue
        rgba = geom_rgba(model, g)
        if rgba[3] <= 0.0:
            continue
        gtype = int(model.geom_type[g])
        size = np.asarray(model.geom_size[g], dtype=np.float64)
        pose = pose_matrix(model.geom_pos[g], model.geom_quat[g])
        center = np.array(model.geom_pos[g], dtype=np.float64)
        radius = float(model.geom_rbound[g])
        if gtype == mujoco.mjtGeom.mjGEOM_PLANE:
            hx = size[0] if size[0] > 0 else plane_extent
            hy = size[1] if size[1] > 0 else plane_extent
            geometry = mg.Box([2 * hx, 2 * hy, 0.002])
            # The plane's surface is its z = 0; the slab hangs just below it.
            local = pose @ pose_matrix([0.0, 0.0, -0.001])
            radius = 0.0
        elif gtype == mujoco.mjtGeom.mjGEOM_SPHERE:
            geometry, local = mg.Sphere(size[0]), pose
        elif gtype == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
            geometry, local = mg.Ellipsoid(size[:3]), pose
        elif gtype == mujoco.mjtGeom.mjGEOM_BOX:
            geometry, local = mg.Box(2 * size[:3]), pose
        elif gtype == mujoco.mjtGeom.mjGEOM_CYLINDER:
            geometry, local = mg.Cylinder(2 * size[1], size[0]), pose @ _CYLINDER_TO_Z
        elif gtype == mujoco.mjtGeom.mjGEOM_CAPSULE:
            geometry, local = mg.TriangularMeshGeometry(*capsule_mesh(size[0], size[1])), pose
        else:
            skipped += 1
            continue
        name = path_name(g, mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or "", "geom")
        obj = mg.Mesh(geometry, _material(rgba)).lower()
        out.append(GeomVisual(g, int(model.geom_bodyid[g]), name, obj, local, center, radius))
    if skipped:
        log.warning(
            "skipped %d non-primitive geoms (mesh, height field or SDF); the viewer draws primitives only", skipped
        )
    return out


def ee_site_ids(model: mujoco.MjModel) -> list[int]:
    """Site ids of the end effectors ``ee_0``, ``ee_1``, ... in index order (those present)."""
    ids = []
    k = 0
    while True:
        sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, f"ee_{k}")
        if sid < 0:
            return ids
        ids.append(sid)
        k += 1


def marker_sphere(radius: float, rgba) -> dict:
    """A small sphere of `radius` [m] (end-effector site marker)."""
    return mg.Mesh(mg.Sphere(radius), _material(rgba)).lower()


def frame_triad(scale: float) -> dict:
    """Red/green/blue x/y/z axes of length `scale` [m]: a pose shown as a small frame."""
    return mg.triad(scale).lower()


def polyline(points: np.ndarray, rgba) -> dict:
    """A line through `points` [m], (K, 3), in the given colour."""
    pts = np.asarray(points, dtype=np.float32)
    return mg.Line(mg.PointsGeometry(pts.T), mg.LineBasicMaterial(color=rgba_to_hex(rgba))).lower()


def ground_grid(lo: np.ndarray, hi: np.ndarray, spacing: float, rgba, *, z: float = 0.0) -> dict:
    """Grid lines on the plane at height `z` [m] covering the rectangle `lo`..`hi` [m] (x, y),
    `spacing` [m] apart.

    Each line is cut into cell-long segments: software WebGL (SwiftShader, used for headless
    screenshots) drops a whole line whose far end lies behind the eye, so long lines that
    pass under the camera would vanish near the robot, where they matter.
    """
    x0, y0 = np.floor(np.asarray(lo[:2]) / spacing) * spacing
    x1, y1 = np.ceil(np.asarray(hi[:2]) / spacing) * spacing
    xs = np.arange(round((x1 - x0) / spacing) + 1) * spacing + x0
    ys = np.arange(round((y1 - y0) / spacing) + 1) * spacing + y0
    segs = []
    for x in xs:  # lines along y
        segs += [((x, ya, z), (x, yb, z)) for ya, yb in zip(ys[:-1], ys[1:])]
    for y in ys:  # lines along x
        segs += [((xa, y, z), (xb, y, z)) for xa, xb in zip(xs[:-1], xs[1:])]
    pts = np.asarray(segs, dtype=np.float32).reshape(-1, 3)
    return mg.LineSegments(mg.PointsGeometry(pts.T), mg.LineBasicMaterial(color=rgba_to_hex(rgba))).lower()


def text_png(text: str, *, pixel_height: int = 48) -> tuple[bytes, int, int]:
    """PNG bytes of dark text on a translucent white card; returns (png, width_px, height_px)."""
    from PIL import Image, ImageDraw, ImageFont

    font = ImageFont.load_default(size=pixel_height)
    left, top, right, bottom = font.getbbox(text)
    pad = pixel_height // 4
    w, h = right - left + 2 * pad, bottom - top + 2 * pad
    img = Image.new("RGBA", (w, h), (255, 255, 255, 0))
    draw = ImageDraw.Draw(img)
    draw.rounded_rectangle([0, 0, w - 1, h - 1], radius=pad, fill=(255, 255, 255, 215))
    draw.text((pad - left, pad - top), text, fill=(20, 20, 30, 255), font=font)
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    return buf.getvalue(), w, h


def text_sprite(text: str, window_fraction: float, fov_deg: float) -> dict:
    """A label that faces the camera and keeps its size on screen: a three.js Sprite whose
    text is `window_fraction` of the window height tall under a vertical field of view of
    `fov_deg` [deg]."""
    png, w_px, h_px = text_png(text)
    # Without size attenuation three.js scales a sprite by its view depth, so a scale s
    # spans s / tan(fov / 2) of the half window height.
    height = 2.0 * window_fraction * np.tan(np.radians(fov_deg) / 2.0)
    width = height * w_px / h_px
    image = mg.PngImage(png)
    texture = mg.ImageTexture(image)
    data = {
        "metadata": {"version": 4.5, "type": "Object"},
        "geometries": [],
        "materials": [],
        "textures": [],
        "images": [],
    }
    material = {
        "uuid": mg.SceneElement().uuid,
        "type": "SpriteMaterial",
        "map": texture.lower_in_object(data),
        "transparent": True,
        "sizeAttenuation": False,
        # Labels stay readable when a robot passes in front of them.
        "depthTest": False,
    }
    data["materials"].append(material)
    data["object"] = {
        "uuid": mg.SceneElement().uuid,
        "type": "Sprite",
        "material": material["uuid"],
        "renderOrder": 10,
        "matrix": [width, 0, 0, 0, 0, height, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1],
    }
    return data
