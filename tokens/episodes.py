"""Episodes -> dynamics RoboTokens (and target-pose tokens) at chosen control steps.

`episode_tokens` reads a `tt.sim.episode.Episode` where it lies (CPU or GPU): it gathers
only the chosen steps of the tensors it needs, with torch indexing on the episode's
device, and never copies a whole episode. Worlds may run different robots (the Episode's
``design_index`` says which); their joint and actuator addresses come from the
`RobotIndex` the tokenizer returned for each robot.

Step choice (paper: 8 steps per episode): ``"random"`` draws distinct steps uniformly
from the executed part of each episode, sorted (motion-to-robot); ``"consecutive"`` takes
a window of consecutive steps at a uniform start (control).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from tt.sim.episode import Episode
from tt.tokens.batch import TokenBatch
from tt.tokens.schema import SCHEMA
from tt.tokens.tokenize import RobotIndex

STEP_MODES = ("random", "consecutive")


def sample_steps(lengths: torch.Tensor, steps: int, mode: str = "random", generator: torch.Generator | None = None,
                 horizon: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Control steps to tokenize per world.

    lengths: executed steps per world, (W,) long (at least one step is always usable: the
    record of a world that ended at step 0 still exists); horizon: the episode length T.
    Returns steps (W, steps) long and valid (W, steps) bool (False where an episode is
    shorter than `steps`).
    """
    if mode not in STEP_MODES:
        raise ValueError(f"mode {mode!r} is not a step mode; valid: {list(STEP_MODES)}")
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    device = lengths.device
    w = lengths.shape[0]
    t = int(horizon if horizon is not None else max(int(lengths.max()), 1) if w else 1)
    n = lengths.clamp(min=1, max=t)
    k = torch.arange(steps, device=device)
    if mode == "consecutive":
        span = (n - steps).clamp(min=0)
        u = _uniform((w,), device, generator)
        start = torch.floor(u * (span + 1).to(u.dtype)).long().clamp(max=span)
        out = start[:, None] + k[None, :]
        return out.clamp(max=t - 1), out < n[:, None]
    # K distinct steps uniformly among the first n: iid draws, sorted, with the rows that
    # drew a step twice drawn again (uniform over K-subsets; ~K^2 / 2n of rows repeat).
    kk = min(steps, t)
    short = n <= kk
    m = torch.where(short, torch.full_like(n, kk + 1), n)
    chosen = torch.empty(w, kk, dtype=torch.long, device=device)
    todo = torch.arange(w, device=device)
    while len(todo):
        draw = (_uniform((len(todo), kk), device, generator) * m[todo, None]).long().clamp(max=t - 1)
        draw = draw.sort(dim=1).values
        chosen[todo] = draw
        dup = (draw.diff(dim=1) == 0).any(1) if kk > 1 else torch.zeros(len(todo), dtype=torch.bool, device=device)
        todo = todo[dup & ~short[todo]]
    # Episodes no longer than K: all their steps, then the last one repeated (invalid).
    all_steps = torch.minimum(k[None, :kk], (n - 1)[:, None])
    chosen = torch.where(short[:, None], all_steps, chosen)
    valid = torch.where(short[:, None], k[None, :kk] < n[:, None], torch.ones_like(chosen, dtype=torch.bool))
    if kk < steps:
        pad = steps - kk
        chosen = torch.cat([chosen, chosen[:, -1:].expand(w, pad)], 1)
        valid = torch.cat([valid, torch.zeros(w, pad, dtype=torch.bool, device=device)], 1)
    return chosen, valid


def _uniform(shape: tuple, device, generator: torch.Generator | None) -> torch.Tensor:
    """U[0, 1) draws on the generator's device (so seeded draws do not depend on `device`)."""
    gdev = generator.device if generator is not None else device
    return torch.rand(shape, device=gdev, generator=generator).to(device)


def _quat_to_mat(q: torch.Tensor) -> torch.Tensor:
    q = q / q.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(*q.shape[:-1], 3, 3)


def _per_world(robots: Sequence[RobotIndex], design_index: np.ndarray, field: str):
    """(W, Emax) addresses of `field` per world (-1 padded) and the mask."""
    arrays = [np.asarray(getattr(r, field)) for r in robots]
    emax = max((len(a) for a in arrays), default=0)
    table = np.full((len(robots), emax), -1, dtype=np.int64)
    for i, a in enumerate(arrays):
        table[i, : len(a)] = a
    out = table[design_index]
    return out, out >= 0


def _gather(x: torch.Tensor, w: torch.Tensor, t: torch.Tensor, cols: torch.Tensor, width: int = 1) -> torch.Tensor:
    """x[w, t, cols + i] for i < width: x (W, T, C), t (W, K), cols (W, E) -> (W, K, E, width).

    Reads just those entries: one 1-D gather through a flat view of a contiguous tensor
    (no copy of the episode), advanced indexing otherwise."""
    idx = cols.clamp(min=0)[:, None, :, None] + torch.arange(width, device=x.device)
    if x.is_contiguous():
        T, C = x.shape[1], x.shape[2]
        flat = (w[:, None, None, None] * T + t[:, :, None, None]) * C + idx
        return x.view(-1)[flat]
    return x[w[:, None, None, None], t[:, :, None, None], idx]


def _pack(name: str, cols: dict[str, torch.Tensor], entity_ids: torch.Tensor, steps: torch.Tensor, valid: torch.Tensor) -> tuple:
    """Attributes (W, K, E, dim) -> tokens (W, K*E, width), ids (W, K*E, 2), mask (W, K*E);
    the values of invalid tokens are zero."""
    t = SCHEMA[name]
    parts = [cols[a.name].reshape(*cols[a.name].shape[:3], a.width) for a in t.attributes]
    v = torch.cat(parts, -1) if len(parts) > 1 else parts[0].clone()
    W, K, E = v.shape[:3]
    ids = torch.empty(W, K, E, 2, dtype=torch.long, device=v.device)
    ids[..., 0] = entity_ids[:, None, :]
    ids[..., 1] = steps[:, :, None]
    v.masked_fill_(~valid[..., None], 0.0)
    return v.reshape(W, K * E, -1), ids.reshape(W, K * E, 2), valid.reshape(W, K * E)


def episode_tokens(episode: Episode, robots: Sequence[RobotIndex], *, steps: int = 8, mode: str = "random",
                   step_index: torch.Tensor | None = None, generator: torch.Generator | None = None,
                   dtype: torch.dtype = torch.float32) -> TokenBatch:
    """Dynamics tokens (free / track link obs, dynamic and ball joint obs, actuator obs,
    control) and target-pose tokens of every world, at `steps` control steps each.

    robots: `RobotIndex` per design, addressed by ``episode.design_index``; step_index:
    (W, K) steps to use instead of sampling (all valid). Returns a torch `TokenBatch` on the
    episode's device, N = W; time IDs are the control step indices.
    """
    dev = episode.qpos.device
    W, T = episode.worlds, episode.steps
    design = episode.design_index.detach().cpu().numpy().astype(np.int64)
    if design.shape != (W,) or (W and (design.min() < 0 or design.max() >= len(robots))):
        raise ValueError(f"episode.design_index must index the {len(robots)} robots given, one per world; got shape {design.shape}"
                         + (f", values {design.min()}..{design.max()}" if W else ""))
    if step_index is None:
        st, valid = sample_steps(episode.lengths().to(dev), steps, mode, generator, horizon=T)
    else:
        st = step_index.to(dev).long()
        if st.ndim != 2 or st.shape[0] != W or (st.numel() and (int(st.min()) < 0 or int(st.max()) >= T)):
            raise ValueError(f"step_index must be (W={W}, K) with values in 0..{T - 1}, got shape {tuple(st.shape)}")
        valid = torch.ones_like(st, dtype=torch.bool)
    K = st.shape[1]
    w = torch.arange(W, device=dev)
    values, ids, mask = {}, {}, {}

    def put(name, cols, ent_ids, ent_mask):
        v, i, m = _pack(name, cols, ent_ids, st, valid[:, :, None] & ent_mask[:, None, :])
        values[name], ids[name], mask[name] = v.to(dtype), i, m

    def tens(a):
        return torch.as_tensor(a, device=dev)

    # Track links and targets: one per end effector.
    A = episode.ee_pos.shape[2]
    counts = {len(r.track_link) for r in robots}
    if counts != {A}:
        raise ValueError(f"episode has {A} end effectors but the robots have {sorted(counts)} track links")
    if A:
        ent = torch.arange(A, device=dev)[None].expand(W, A)
        ok = torch.ones(W, A, dtype=torch.bool, device=dev)
        for name, p, q in (("track_link_obs", episode.ee_pos, episode.ee_quat), ("target_pose", episode.target_pos, episode.target_quat)):
            pos = p[w[:, None], st]  # (W, K, A, 3)
            rot = _quat_to_mat(q[w[:, None], st]).reshape(W, K, A, 9)
            put(name, {"pos": pos, "rot": rot}, ent, ok)

    # Free links: body pose from the free joint's qpos, then the link's offset in the body.
    adr, ok_np = _per_world(robots, design, "free_qposadr")
    if adr.shape[1]:
        F = adr.shape[1]
        a = tens(adr)
        raw = _gather(episode.qpos, w, st, a, 7)  # (W, K, F, 7)
        rb = _quat_to_mat(raw[..., 3:])
        off_r = np.zeros((W, F, 3, 3))
        off_p = np.zeros((W, F, 3))
        for i, r in enumerate(robots):
            sel = design == i
            f = len(r.free_qposadr)
            off_r[sel, :f], off_p[sel, :f] = r.free_offset_rot, r.free_offset_pos
        orr = tens(off_r).to(rb.dtype)[:, None]
        opp = tens(off_p).to(rb.dtype)[:, None]
        rot = rb @ orr
        pos = (rb @ opp[..., None])[..., 0] + raw[..., :3]
        put("free_link_obs", {"pos": pos, "rot": rot.reshape(W, K, F, 9)}, torch.arange(F, device=dev)[None].expand(W, F), tens(ok_np))

    # Hinge / slide joints.
    qadr, ok_np = _per_world(robots, design, "dyna_qposadr")
    if qadr.shape[1]:
        vadr, _ = _per_world(robots, design, "dyna_dofadr")
        D = qadr.shape[1]
        put("dyna_joint_obs", {"qpos": _gather(episode.qpos, w, st, tens(qadr)), "qvel": _gather(episode.qvel, w, st, tens(vadr))},
            torch.arange(D, device=dev)[None].expand(W, D), tens(ok_np))

    # Ball joints: quaternion with w >= 0 (q and -q are the same rotation), local angular velocity.
    qadr, ok_np = _per_world(robots, design, "ball_qposadr")
    if qadr.shape[1]:
        vadr, _ = _per_world(robots, design, "ball_dofadr")
        B = qadr.shape[1]
        quat = _gather(episode.qpos, w, st, tens(qadr), 4)
        quat = torch.where(quat[..., :1] < 0, -quat, quat)
        put("ball_joint_obs", {"quat": quat, "angvel": _gather(episode.qvel, w, st, tens(vadr), 3)},
            torch.arange(B, device=dev)[None].expand(W, B), tens(ok_np))

    # Actuators: observation and the clean command.
    aadr, ok_np = _per_world(robots, design, "actuator_mj")
    if aadr.shape[1]:
        nA = aadr.shape[1]
        a = tens(aadr)
        ent = torch.arange(nA, device=dev)[None].expand(W, nA)
        put("actuator_obs", {"velocity": _gather(episode.act_vel, w, st, a), "force": _gather(episode.act_force, w, st, a)}, ent, tens(ok_np))
        put("control", {"target": _gather(episode.action, w, st, a)}, ent, tens(ok_np))

    return TokenBatch(values, ids, mask)
