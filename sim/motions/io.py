"""Motion files, resampling to 50 Hz, and planar SE(2) augmentation.

Files:
  ``.npz``: ``pos`` (T, 3) [m], ``quat`` (T, 4) (w, x, y, z), ``dt`` [s], optional
  ``pos2`` / ``quat2`` for a second end effector, optional ``name``. `save_npz` writes
  this layout and `load_npz` reads it back bit for bit.
  UMI zarr stores (``.zarr`` folder or ``.zarr.zip``): ``data/robot0_eef_pos`` (N, 3),
  ``data/robot0_eef_rot_axis_angle`` (N, 3), optional ``robot1_*``, and
  ``meta/episode_ends`` (cumulative end index of each episode).
Every loader resamples to `MOTION_DT` (linear in position, slerp in rotation) and raises
`MotionError` naming the file and field for empty, non-finite or non-unit data.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from tt.kernels.files import CorruptFileError, atomic_write, read_npz
from tt.sim.motions.base import (
    MOTION_DT,
    Motion,
    MotionError,
    quat_continuous,
    quat_from_rotvec,
    quat_mul,
    quat_slerp,
)

#: Relative tolerance on sample periods treated as already being `MOTION_DT`.
_DT_RTOL = 1e-9

#: Rotation (w, x, y, z) from tt's end-effector frame to UMI's TCP frame. UMI's TCP frame
#: is the GoPro optical frame moved to the finger tips (z along the approach, y down the
#: image); tt's has x along the approach and z up when level. Applied on the right:
#: q_tt = q_umi ⊗ UMI_TOOL_QUAT.
UMI_TOOL_QUAT = (0.5, 0.5, -0.5, 0.5)

#: Longest motion after resampling [control steps] (10 hours at 50 Hz): a longer one is a wrong dt.
MAX_STEPS = 1_800_000

#: Default recording rate of UMI stores [Hz] (GoPro video, nominally 60 frames per second).
UMI_HZ = 60.0


# ------------------------------------------------------------------ resampling


def resample(pos: np.ndarray, quat: np.ndarray, src_dt: float, dt: float = MOTION_DT) -> tuple[np.ndarray, np.ndarray]:
    """Resample a trajectory from period `src_dt` to `dt` [s].

    pos: (N, A, 3) [m]; quat: (N, A, 4) unit (w, x, y, z). Output samples lie at
    t = k dt for every k with k dt <= (N - 1) src_dt: pos by linear interpolation,
    quat by slerp between the bracketing samples. Returns pos (T, A, 3), quat (T, A, 4).
    """
    pos = np.asarray(pos, dtype=np.float64)
    quat = np.asarray(quat, dtype=np.float64)
    if not (np.isfinite(src_dt) and src_dt > 0 and np.isfinite(dt) and dt > 0):
        raise MotionError(f"sample periods must be positive seconds, got src_dt={src_dt}, dt={dt}")
    n = pos.shape[0]
    if n == 0:
        raise MotionError("cannot resample an empty trajectory (T = 0)")
    if abs(src_dt - dt) <= _DT_RTOL * dt or n == 1:
        return pos, quat
    end = (n - 1) * src_dt
    if not end / dt <= MAX_STEPS:
        raise MotionError(
            f"a motion of {n} samples every {src_dt:g} s lasts {end:g} s, more than {MAX_STEPS:,} steps of {dt:g} s"
        )
    t = np.arange(int(np.floor(end / dt + 1e-9)) + 1) * dt
    x = t / src_dt
    i = np.minimum(np.floor(x).astype(int), n - 2)
    s = x - i
    p = pos[i] + (pos[i + 1] - pos[i]) * s[:, None, None]
    q = quat_slerp(quat[i], quat[i + 1], np.broadcast_to(s[:, None], (t.size, quat.shape[1])))
    return p, quat_continuous(q)


def resample_motion(motion: Motion, dt: float = MOTION_DT) -> Motion:
    """`motion` resampled to period `dt` [s] (itself when already at `dt`)."""
    if abs(motion.dt - dt) <= _DT_RTOL * dt:
        return motion
    pos, quat = resample(motion.pos, motion.quat, motion.dt, dt)
    return Motion(motion.name, pos, quat, dt, meta=dict(motion.meta, source_dt=motion.dt))


# ------------------------------------------------------------------ validation of loaded arrays


def _check_array(path: Path, field: str, arr: Any, width: int) -> np.ndarray:
    """A (T, width) float array, or `MotionError` naming the file and field."""
    if getattr(arr, "dtype", np.dtype("f8")).kind not in "fiu":
        raise MotionError(f"{path}: field {field!r} holds {np.asarray(arr).dtype} values, not real numbers")
    try:
        a = np.asarray(arr, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise MotionError(f"{path}: field {field!r} is not numeric ({e})") from None
    if a.ndim != 2 or a.shape[1] != width:
        raise MotionError(f"{path}: field {field!r} must have shape (T, {width}), got {a.shape}")
    if a.shape[0] == 0:
        raise MotionError(f"{path}: field {field!r} is empty (T = 0)")
    bad = ~np.isfinite(a)
    if bad.any():
        raise MotionError(f"{path}: field {field!r} has NaN/inf (first at step {int(np.argwhere(bad)[0, 0])})")
    return a


def _check_quat(path: Path, field: str, q: np.ndarray) -> None:
    norms = np.linalg.norm(q, axis=-1)
    off = np.abs(norms - 1.0) > 1e-3
    if off.any():
        k = int(np.argmax(off))
        raise MotionError(
            f"{path}: field {field!r} at step {k} has norm {norms[k]:.4f}; quaternions must be unit (w, x, y, z)"
        )


def _motion(path: Path, name: str, pos: np.ndarray, quat: np.ndarray, dt: float, meta: dict) -> Motion:
    """Build, resample to 50 Hz, and prefix any remaining error with the file name."""
    try:
        pos, quat = resample(pos, quat, dt)
        return Motion(name, pos, quat, MOTION_DT, meta=meta)
    except MotionError as e:
        raise MotionError(f"{path}: {e}") from None


# ------------------------------------------------------------------ npz


def save_npz(motion: Motion, path: str | Path) -> None:
    """Write `motion` (one or two end effectors) as ``.npz``; `load_npz` reads it back exactly."""
    if motion.arms > 2:
        raise MotionError(f"motion {motion.name!r}: the npz layout holds 1 or 2 end effectors, not {motion.arms}")
    arrays = {
        "pos": motion.pos[:, 0],
        "quat": motion.quat[:, 0],
        "dt": np.float64(motion.dt),
        "name": np.str_(motion.name),
    }
    if motion.arms == 2:
        arrays |= {"pos2": motion.pos[:, 1], "quat2": motion.quat[:, 1]}
    with atomic_write(path) as f:  # through a handle: np.savez appends .npz to names without it
        np.savez(f, **arrays)


def _scalar(path: Path, data: dict, key: str) -> float:
    """``data[key]`` as one real number, or `MotionError` naming the file and field."""
    a = data[key]
    if a.size != 1 or a.dtype.kind not in "fiu":
        raise MotionError(f"{path}: field {key!r} must be one number of seconds, got {a.dtype}{a.shape}")
    return float(a.reshape(()))


def load_npz(path: str | Path) -> Motion:
    """A motion from ``.npz`` (layout in the module docstring), resampled to 50 Hz."""
    path = Path(path)
    try:
        data = read_npz(path, "motion file")
    except CorruptFileError as e:
        raise MotionError(str(e)) from None
    for key in ("pos", "quat", "dt"):
        if key not in data:
            raise MotionError(f"{path}: missing field {key!r}; found {sorted(data)}")
    if ("pos2" in data) != ("quat2" in data):
        raise MotionError(f"{path}: a second end effector needs both 'pos2' and 'quat2'; found {sorted(data)}")
    dt = _scalar(path, data, "dt")
    if not (np.isfinite(dt) and dt > 0):
        raise MotionError(f"{path}: field 'dt' must be a positive number of seconds, got {dt}")
    arms = [("pos", "quat")] + ([("pos2", "quat2")] if "pos2" in data else [])
    pos, quat = [], []
    for pk, qk in arms:
        pos.append(_check_array(path, pk, data[pk], 3))
        quat.append(_check_array(path, qk, data[qk], 4))
        _check_quat(path, qk, quat[-1])
    lengths = {k: a.shape[0] for (k, _), a in zip(arms, pos)} | {k: a.shape[0] for (_, k), a in zip(arms, quat)}
    if len(set(lengths.values())) != 1:
        raise MotionError(f"{path}: fields have different lengths {lengths}")
    name = path.stem
    if "name" in data:
        if data["name"].dtype.kind not in "US" or data["name"].size != 1:
            raise MotionError(f"{path}: field 'name' must be one string, got {data['name'].dtype}{data['name'].shape}")
        name = str(data["name"].reshape(()))
    meta = {"source": str(path), "source_dt": dt}
    return _motion(path, name, np.stack(pos, axis=1), np.stack(quat, axis=1), dt, meta)


# ------------------------------------------------------------------ UMI zarr


def _open_zarr(path: Path):
    import zarr

    try:
        if path.name.endswith(".zip"):
            return zarr.open_group(zarr.storage.ZipStore(path, mode="r"), mode="r")
        return zarr.open_group(str(path), mode="r")
    except Exception as e:  # zarr raises several unrelated types for a missing or foreign store
        raise MotionError(f"{path}: cannot open as a zarr store ({type(e).__name__}: {e})") from None


def _umi_episode_ends(path: Path, root) -> np.ndarray:
    try:
        ends = np.asarray(root["meta/episode_ends"][:])
    except KeyError:
        raise MotionError(f"{path}: missing array 'meta/episode_ends'") from None
    if ends.ndim != 1 or ends.size == 0 or np.any(np.diff(ends) < 0) or ends[0] < 0:
        raise MotionError(f"{path}: 'meta/episode_ends' must be a non-empty increasing 1-D array, got {ends!r}")
    return ends.astype(np.int64)


def umi_episode_count(path: str | Path) -> int:
    """Number of episodes in a UMI zarr store."""
    path = Path(path)
    return int(_umi_episode_ends(path, _open_zarr(path)).size)


def load_umi_zarr(
    path: str | Path,
    episode: int = 0,
    *,
    hz: float = UMI_HZ,
    tool_quat: tuple[float, float, float, float] | np.ndarray = UMI_TOOL_QUAT,
    name: str | None = None,
) -> Motion:
    """One episode of a UMI-format zarr store as a 50 Hz motion.

    episode: index into ``meta/episode_ends``; hz: recording rate [Hz] of the store;
    tool_quat: fixed rotation (w, x, y, z) applied on the right of every recorded
    orientation (default `UMI_TOOL_QUAT`, UMI's TCP frame to tt's; identity keeps
    UMI's). Arms robot0 and, when present, robot1 become end effectors 0 and 1. Positions
    stay in the store's frame; `recenter` moves them into a robot's workspace.
    """
    path = Path(path)
    if not (np.isfinite(hz) and hz > 0):
        raise MotionError(f"{path}: hz must be a positive rate, got {hz}")
    root = _open_zarr(path)
    ends = _umi_episode_ends(path, root)
    if not isinstance(episode, (int, np.integer)) or not 0 <= episode < ends.size:
        raise MotionError(f"{path}: episode {episode!r} does not exist; valid: 0..{ends.size - 1}")
    start = 0 if episode == 0 else int(ends[episode - 1])
    stop = int(ends[episode])
    if stop <= start:
        raise MotionError(f"{path}: episode {episode} is empty (samples {start}..{stop})")
    robots = ["robot0"] + (["robot1"] if "data/robot1_eef_pos" in root else [])
    fix = np.asarray(tool_quat, dtype=np.float64)
    if fix.shape != (4,) or abs(np.linalg.norm(fix) - 1.0) > 1e-6:
        raise MotionError(f"tool_quat must be a unit quaternion (w, x, y, z), got {tool_quat!r}")
    pos, quat = [], []
    for r in robots:
        fields = {}
        for f, width in (("eef_pos", 3), ("eef_rot_axis_angle", 3)):
            key = f"data/{r}_{f}"
            try:
                arr = root[key]
            except KeyError:
                raise MotionError(f"{path}: missing array {key!r}") from None
            if arr.shape[0] < stop:
                raise MotionError(f"{path}: {key!r} has {arr.shape[0]} samples, meta/episode_ends needs {stop}")
            fields[f] = _check_array(path, key, arr[start:stop], width)
        pos.append(fields["eef_pos"])
        quat.append(quat_mul(quat_continuous(quat_from_rotvec(fields["eef_rot_axis_angle"])), fix))
    meta = {"source": str(path), "episode": int(episode), "source_dt": 1.0 / hz}
    return _motion(
        path, name or f"{path.name.split('.')[0]}:{episode}", np.stack(pos, 1), np.stack(quat, 1), 1.0 / hz, meta
    )


# ------------------------------------------------------------------ dispatch


def load_motion_file(path: str | Path, *, place: bool = True, **kwargs: Any) -> Motion:
    """Load by suffix: ``.npz`` -> `load_npz`; ``.zarr`` / ``.zarr.zip`` -> `load_umi_zarr` (kwargs go there).

    place: move the motion to the robot's base as the library's motions are (`place_at_base`);
    False keeps the file's own frame.
    """
    path = Path(path)
    if not path.exists():
        raise MotionError(f"{path}: no such file")
    lower = path.name.lower()
    if lower.endswith(".npz"):
        if kwargs:
            raise MotionError(f"{path}: load_npz takes no options, got {sorted(kwargs)}")
        motion = load_npz(path)
    elif lower.endswith(".zarr") or lower.endswith(".zarr.zip"):
        motion = load_umi_zarr(path, **kwargs)
    else:
        raise MotionError(f"{path}: unknown motion file type; valid suffixes: .npz, .zarr, .zarr.zip")
    return place_at_base(motion) if place else motion


def resolve_motion(spec: str) -> Motion:
    """A motion from a library name (``toss``, ``toss:7``) or a file path."""
    from tt.sim.motions.registry import SKILLS, get_motion

    if spec.split(":")[0] in SKILLS:
        return get_motion(spec)
    if Path(spec).exists():
        return load_motion_file(spec)
    raise MotionError(f"{spec!r} is neither a motion name ({', '.join(SKILLS)}; optionally name:seed) nor a file")


# ------------------------------------------------------------------ SE(2) augmentation


def augment_se2(pos, quat, yaw, dx, dy):
    """Rotate trajectories about the world z axis by `yaw` [rad], then shift them by (dx, dy) [m].

    pos: (B, ..., 3); quat: (B, ..., 4) (w, x, y, z); yaw, dx, dy: scalars or shape (B,)
    (one transform per leading entry). numpy arrays or torch tensors (same type out,
    differentiable in torch). Gravity fixes z, so this planar group is the symmetry the
    paper augments with. Returns (pos, quat).
    """
    is_torch = type(pos).__module__.startswith("torch")
    if is_torch:
        import torch

        def as_arr(v):
            return torch.as_tensor(v, dtype=pos.dtype, device=pos.device)

        stack = lambda xs: torch.stack(xs, dim=-1)  # noqa: E731
        cos, sin = torch.cos, torch.sin
    else:
        pos = np.asarray(pos, dtype=np.float64)
        quat = np.asarray(quat, dtype=np.float64)

        def as_arr(v):
            return np.asarray(v, dtype=np.float64)

        stack = lambda xs: np.stack(xs, axis=-1)  # noqa: E731
        cos, sin = np.cos, np.sin
    if pos.shape[-1] != 3 or quat.shape[-1] != 4 or pos.shape[:-1] != quat.shape[:-1]:
        raise MotionError(
            "augment_se2 needs pos (..., 3) and quat (..., 4) with equal leading shapes, got "
            f"{tuple(pos.shape)} and {tuple(quat.shape)}"
        )

    def per_batch(v, field):
        v = as_arr(v)
        if v.ndim == 0:
            return v
        if v.ndim != 1 or v.shape[0] != pos.shape[0]:
            raise MotionError(f"augment_se2: {field} must be a scalar or shape ({pos.shape[0]},), got {tuple(v.shape)}")
        return v.reshape((-1,) + (1,) * (pos.ndim - 2))

    yaw, dx, dy = per_batch(yaw, "yaw"), per_batch(dx, "dx"), per_batch(dy, "dy")
    c, s = cos(yaw), sin(yaw)
    x, y, z = pos[..., 0], pos[..., 1], pos[..., 2]
    new_pos = stack([c * x - s * y + dx, s * x + c * y + dy, z])
    # Left-multiplying by the z rotation (cos(yaw/2), 0, 0, sin(yaw/2)), expanded.
    ch, sh = cos(yaw / 2), sin(yaw / 2)
    w, qx, qy, qz = quat[..., 0], quat[..., 1], quat[..., 2], quat[..., 3]
    new_quat = stack([ch * w - sh * qz, ch * qx - sh * qy, ch * qy + sh * qx, ch * qz + sh * w])
    return new_pos, new_quat


def augment_motion(
    motion: Motion,
    seed: int,
    *,
    max_yaw: float = np.pi / 8,
    max_shift: float = 0.03,
    pivot: tuple[float, float] = (0.0, 0.0),
) -> Motion:
    """`motion` under a random planar transform drawn from `seed`.

    yaw ~ U(-max_yaw, max_yaw) [rad] about the vertical through `pivot` (x, y) [m], then
    a shift with each of dx, dy ~ U(-max_shift, max_shift) [m]. The default pivot is the
    single arm's base, about which a rotation keeps every target's distance from the
    shoulder. The transform is recorded in ``meta["se2"]``.
    """
    rng = np.random.default_rng(seed)
    yaw = float(rng.uniform(-max_yaw, max_yaw))
    sx, sy = (float(v) for v in rng.uniform(-max_shift, max_shift, size=2))
    c, s = np.cos(yaw), np.sin(yaw)
    px, py = pivot
    # Rotation about the pivot = rotation about the origin plus pivot - R pivot.
    dx = px - (c * px - s * py) + sx
    dy = py - (s * px + c * py) + sy
    pos, quat = augment_se2(motion.pos, motion.quat, yaw, dx, dy)
    meta = dict(motion.meta, se2={"seed": int(seed), "yaw": yaw, "dx": float(dx), "dy": float(dy)})
    return Motion(f"{motion.name}+se2:{seed}", pos, quat, motion.dt, meta=meta)


def for_space(motions: Sequence[Motion], space: str) -> list[Motion]:
    """Library motions moved into the workspace of design space `space` (its `motion_offset`).

    Motions start over the base (`place_at_base`); a space that does not use that placement
    (`DesignSpace.places_motions`, the quadruped) gets them back where they were written, for
    table-top arms at the origin. A robot whose hands work in front of its base at counter
    height (the mobile bimanual, `tt.sim.designs.bimanual.MOTION_OFFSET`) declares the
    translation that puts them there, recorded in ``meta["space_offset"]``: the motion as
    written is ``pos - space_offset - placed_shift``.
    """
    from tt.sim.designs import get_space

    sp = get_space(space)
    offset = np.asarray(sp.motion_offset, dtype=np.float64)
    out = []
    for m in motions:
        if m.arms != sp.ee_count:
            raise MotionError(f"motion {m.name!r} has {m.arms} end effector(s); space {space!r} has {sp.ee_count}")
        if not sp.places_motions and "placed_shift" in m.meta:
            # Back where the skill (or file) had it: this robot does not use the base placement.
            meta = {k: v for k, v in m.meta.items() if k != "placed_shift"}
            m = Motion(m.name, m.pos - np.asarray(m.meta["placed_shift"]), m.quat, m.dt, meta=meta)
        if np.any(offset != 0.0):
            m = Motion(m.name, m.pos + offset, m.quat, m.dt, meta=dict(m.meta, space_offset=offset.tolist()))
        out.append(m)
    return out


def recenter(motion: Motion, center: tuple[float, float, float] | np.ndarray) -> Motion:
    """`motion` translated so the middle of its position bounding box (all arms) is `center` [m]."""
    pos = motion.pos
    mid = 0.5 * (pos.reshape(-1, 3).min(0) + pos.reshape(-1, 3).max(0))
    shift = np.asarray(center, dtype=np.float64) - mid
    return Motion(
        motion.name, pos + shift, motion.quat, motion.dt, meta=dict(motion.meta, recenter_shift=shift.tolist())
    )


#: Below this distance [m] a motion already counts as placed, so that placing a placed
#: motion (e.g. one saved with `save_npz` and loaded again) returns it bit for bit.
_PLACED_TOL = 1e-9


def place_at_base(motion: Motion, base_xy: tuple[float, float] = (0.0, 0.0)) -> Motion:
    """`motion` translated in the ground plane so that it starts over the robot's base.

    The mean over end effectors of the first pose's (x, y) moves to `base_xy` [m]; heights
    and orientations are kept. This is how the paper's datasets place every demonstration
    relative to the robot (after augmentation), and how tt places its library and loaded
    files: where the motion then lies relative to the arm (beside it, behind it, overhead,
    at long reach) is for the design, its mount pose and link lengths, to handle. The
    shift is recorded in ``meta["placed_shift"]``.
    """
    shift_xy = np.asarray(base_xy, dtype=np.float64) - motion.pos[0, :, :2].mean(axis=0)
    if np.all(np.abs(shift_xy) <= _PLACED_TOL):
        return motion
    shift = np.array([shift_xy[0], shift_xy[1], 0.0])
    meta = dict(motion.meta, placed_shift=(shift + np.asarray(motion.meta.get("placed_shift", 0.0))).tolist())
    return Motion(motion.name, motion.pos + shift, motion.quat, motion.dt, meta=meta)
