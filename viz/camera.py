"""Camera framing for meshcat scenes, and the pinhole model that says where points land.

Meshcat's orbit controls always aim the camera at the world origin of the viewer, so a
scene is framed by translating its content so that the point of interest sits at the
origin (`CameraView.center`) and placing the eye at `CameraView.eye` relative to it. The
world z axis stays up on screen.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tt.kernels.errors import TTError


class CameraError(TTError):
    """Camera options out of range; the message names the field."""


@dataclass(frozen=True)
class CameraOptions:
    """How a scene is framed.

    azimuth_deg: direction from the scene centre to the eye in the ground plane [deg],
        measured from +x towards +y; -60 looks at an arm that reaches along +x from its side.
    elevation_deg: angle of the eye above the ground plane [deg], in (-89, 89).
    fov_deg: vertical field of view [deg], in (5, 120).
    aspect: width / height of the window the framing must fit (800 x 600 -> 4/3).
    margin: factor >= 1 on the distance that just fits the content.
    """

    azimuth_deg: float = -60.0
    elevation_deg: float = 25.0
    fov_deg: float = 40.0
    aspect: float = 4.0 / 3.0
    margin: float = 1.12

    def __post_init__(self) -> None:
        if not -89.0 < self.elevation_deg < 89.0:
            raise CameraError(f"elevation_deg = {self.elevation_deg}; valid: strictly between -89 and 89")
        if not 5.0 < self.fov_deg < 120.0:
            raise CameraError(f"fov_deg = {self.fov_deg}; valid: strictly between 5 and 120")
        if not self.aspect > 0:
            raise CameraError(f"aspect = {self.aspect}; valid: > 0")
        if not self.margin >= 1.0:
            raise CameraError(f"margin = {self.margin}; valid: >= 1")

    def forward(self) -> np.ndarray:
        """Unit viewing direction (from the eye towards the centre), (3,)."""
        az, el = np.radians(self.azimuth_deg), np.radians(self.elevation_deg)
        return -np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


@dataclass(frozen=True)
class CameraView:
    """A framed view.

    center: world point shown at the middle of the window [m], (3,).
    eye: eye position relative to `center` [m], (3,).
    fov_deg: vertical field of view [deg].
    """

    center: np.ndarray
    eye: np.ndarray
    fov_deg: float
    _basis: tuple = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        f = -np.asarray(self.eye, dtype=np.float64)
        f = f / np.linalg.norm(f)
        r = np.cross(f, [0.0, 0.0, 1.0])
        r = r / np.linalg.norm(r)
        u = np.cross(r, f)
        object.__setattr__(self, "_basis", (r, u, f))

    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit right, up and forward directions of the camera in the world, each (3,)."""
        return self._basis

    def project(self, points: np.ndarray, width: int, height: int) -> np.ndarray:
        """Pixel coordinates (column, row) of world points [m] (N, 3) in a `width` x `height`
        window, row 0 at the top; points behind the eye come back as NaN. (N, 2)."""
        r, u, f = self._basis
        d = np.asarray(points, dtype=np.float64) - np.asarray(self.center) - np.asarray(self.eye)
        depth = d @ f
        scale = (height / 2.0) / np.tan(np.radians(self.fov_deg) / 2.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            col = width / 2.0 + scale * (d @ r) / depth
            row = height / 2.0 - scale * (d @ u) / depth
        out = np.stack([col, row], -1)
        out[depth <= 0] = np.nan
        return out


def frame_points(points: np.ndarray, radii: np.ndarray, options: CameraOptions) -> CameraView:
    """The view along `options`' direction that fits spheres at `points` [m] (N, 3) with
    `radii` [m] (N,) in the window, centred on their bounding box."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    rad = np.broadcast_to(np.asarray(radii, dtype=np.float64), p.shape[:1])
    if p.shape[0] == 0:
        raise CameraError("nothing to frame: no points given")
    lo = (p - rad[:, None]).min(0)
    hi = (p + rad[:, None]).max(0)
    center = (lo + hi) / 2.0
    f = options.forward()
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    tan_v = np.tan(np.radians(options.fov_deg) / 2.0)
    tan_h = tan_v * options.aspect
    # The box centre is not where the content's image is centred (perspective makes near
    # parts look bigger), so re-aim at the middle of the image extent a few times.
    for _ in range(4):
        q = p - center
        along = q @ f  # how far beyond the centre each point lies, seen from the eye
        # A point at depth D + along must satisfy |offset| + radius <= tan * depth.
        need_h = options.margin * (np.abs(q @ r) + rad) / tan_h - along
        need_v = options.margin * (np.abs(q @ u) + rad) / tan_v - along
        need_front = rad + 0.05 - along  # keep everything in front of the eye
        distance = float(max(need_h.max(), need_v.max(), need_front.max()))
        depth = distance + along
        x_lo, x_hi = ((q @ r - rad) / depth).min(), ((q @ r + rad) / depth).max()
        y_lo, y_hi = ((q @ u - rad) / depth).min(), ((q @ u + rad) / depth).max()
        center = center + distance * ((x_lo + x_hi) / 2.0 * r + (y_lo + y_hi) / 2.0 * u)
    q = p - center
    along = q @ f
    need_h = options.margin * (np.abs(q @ r) + rad) / tan_h - along
    need_v = options.margin * (np.abs(q @ u) + rad) / tan_v - along
    distance = float(max(need_h.max(), need_v.max(), (rad + 0.05 - along).max()))
    return CameraView(center=center, eye=-distance * f, fov_deg=options.fov_deg)
