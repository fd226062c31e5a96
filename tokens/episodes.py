"""Episodes -> dynamics RoboTokens (and target-pose tokens) at chosen control steps.

`episode_tokens` reads a `tt.sim.episode.Episode` where it lies (CPU or GPU): it copies
only the chosen steps (whole rows, once per tensor it needs) with torch indexing on the
episode's device, never a whole episode, and picks every token's entries from those rows
with one gather per token type. Worlds may run different robots (the Episode's
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

from tt.kernels.errors import TTError
from tt.sim.episode import Episode
from tt.tokens.batch import TokenBatch
from tt.tokens.tokenize import RobotIndex

STEP_MODES = ("random", "consecutive")


def sample_steps(
    lengths: torch.Tensor,
    steps: int,
    mode: str = "random",
    generator: torch.Generator | None = None,
    horizon: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Control steps to tokenize per world.

    lengths: executed steps per world, (W,) long (at least one step is always usable: the
    record of a world that ended at step 0 still exists); horizon: the episode length T.
    Returns steps (W, steps) long and valid (W, steps) bool (False where an episode is
    shorter than `steps`).
    """
    if mode not in STEP_MODES:
        raise TTError(f"mode {mode!r} is not a step mode; valid: {list(STEP_MODES)}")
    if steps < 1:
        raise TTError(f"steps must be >= 1, got {steps}")
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
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(*q.shape[:-1], 3, 3)


# Address fields of RobotIndex that episode tokens read, each padded into one (R, Emax)
# table: -1 marks entities a robot lacks.
_ADDRESS_FIELDS = ("free_qposadr", "dyna_qposadr", "dyna_dofadr", "ball_qposadr", "ball_dofadr", "actuator_mj")


def _stack_padded(arrays: list[np.ndarray], trailing: tuple, fill, dtype) -> np.ndarray:
    """(R, Emax, *trailing) array of R arrays of shapes (E_r, *trailing), `fill` past E_r.

    One concatenation and one masked assignment instead of a Python loop of row assignments."""
    lens = np.fromiter(map(len, arrays), dtype=np.int64, count=len(arrays))
    emax = int(lens.max(initial=0))
    out = np.full((len(arrays), emax, *trailing), fill, dtype=dtype)
    if emax:
        # Empty arrays may lack the trailing dimensions (shape (0,)): leave them out.
        out[np.arange(emax) < lens[:, None]] = np.concatenate([a for a, n in zip(arrays, lens.tolist()) if n])
    return out


def _robot_tables(robots: Sequence[RobotIndex]) -> dict[str, np.ndarray]:
    """Padded tables of every robot's addresses, (R, Emax) int64 (-1 padded), and free-link
    offsets, (R, Fmax, 3, 3) and (R, Fmax, 3) float64 (zero padded). Tables of entities
    no robot has are (R, 0) (their partner fields are not read)."""
    tables = {}
    for f in _ADDRESS_FIELDS:
        partner = {"dyna_dofadr": "dyna_qposadr", "ball_dofadr": "ball_qposadr"}.get(f)
        if partner is not None and not tables[partner].shape[1]:
            tables[f] = tables[partner]
            continue
        tables[f] = _stack_padded([getattr(r, f) for r in robots], (), -1, np.int64)
    if tables["free_qposadr"].shape[1]:
        tables["free_offset_rot"] = _stack_padded([r.free_offset_rot for r in robots], (3, 3), 0.0, np.float64)
        tables["free_offset_pos"] = _stack_padded([r.free_offset_pos for r in robots], (3,), 0.0, np.float64)
    return tables


def _step_rows(x: torch.Tensor, rows: torch.Tensor, w: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """x[w, t] flattened: x (W, T, ...) -> (W*K, C); rows = w*T + t, w and t (W*K,).

    Whole rows are copied (contiguous memory, one index_select) rather than single
    entries: picking entries one by one costs several times more."""
    c = int(np.prod(x.shape[2:]))
    if x.is_contiguous():
        return x.view(x.shape[0] * x.shape[1], c).index_select(0, rows)
    return x[w, t].reshape(len(rows), c)


def _step_buffer(
    episode: Episode, names: Sequence[str], rows, w, t, invalid: torch.Tensor | None
) -> tuple[torch.Tensor, dict, int]:
    """The chosen steps of the episode tensors `names` side by side, and one zero column.

    Returns the buffer (W*K, C) in the tensors' promoted dtype, the first column of each
    tensor, and the zero column (what padded entities read). Rows of invalid steps are
    zero (invalid: (n,) flat row numbers, or None)."""
    parts, start, c = [], {}, 0
    for n in names:
        x = getattr(episode, n)
        start[n] = c
        parts.append(_step_rows(x, rows, w, t))
        c += parts[-1].shape[1]
    parts.append(torch.zeros(len(rows), 1, dtype=parts[0].dtype, device=rows.device))
    buf = torch.cat(parts, 1)
    if invalid is not None:
        buf.index_fill_(0, invalid, 0.0)
    return buf, start, c


def _columns(
    addr: np.ndarray, width: int, start: int, limit: int, zero: int, field: str, source: str, used: np.ndarray
) -> np.ndarray:
    """Step-buffer columns of `width` entries from each address: addr (R, E) (-1 padded) ->
    (R, E, width); padded entities read the zero column.

    limit: column count of the episode tensor `source`; the addresses of the robots `used`
    (R,) bool must fit in it."""
    live = addr[used]
    if live.size and int(live.max()) + width > limit:
        bad = int(np.argmax((addr.max(1) + width > limit) & used))
        raise TTError(
            f"robots[{bad}].{field} reaches column {int(addr[bad].max()) + width - 1} of episode.{source}, "
            f"which has {limit} columns: the episode was not rolled out with this robot"
        )
    return np.where(addr[..., None] >= 0, start + addr[..., None] + np.arange(width), zero)


def _token_ids(E: int, steps: torch.Tensor) -> torch.Tensor:
    """(W, K*E, 2) IDs (entity, control step) of entities 0..E-1 at steps (W, K)."""
    W, K = steps.shape
    ids = torch.empty(W, K, E, 2, dtype=torch.long, device=steps.device)
    ids[..., 0] = torch.arange(E, device=steps.device)
    ids[..., 1] = steps[:, :, None]
    return ids.reshape(W, K * E, 2)


def episode_tokens(
    episode: Episode,
    robots: Sequence[RobotIndex],
    *,
    steps: int = 8,
    mode: str = "random",
    step_index: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
) -> TokenBatch:
    """Dynamics tokens (free / track link obs, dynamic and ball joint obs, actuator obs,
    control) and target-pose tokens of every world, at `steps` control steps each.

    robots: `RobotIndex` per design, addressed by ``episode.design_index``; step_index:
    (W, K) steps to use instead of sampling (all valid). Returns a torch `TokenBatch` on the
    episode's device, N = W; time IDs are the control step indices. Tokens of invalid
    steps and padded entities are zero.
    """
    dev = episode.qpos.device
    W, T = episode.worlds, episode.steps
    design = episode.design_index.detach().cpu().numpy().astype(np.int64)
    if design.shape != (W,) or (W and (design.min() < 0 or design.max() >= len(robots))):
        raise TTError(
            f"episode.design_index must index the {len(robots)} robots given, one per world; got shape {design.shape}"
            + (f", values {design.min()}..{design.max()}" if W else "")
        )
    if step_index is None:
        st, valid = sample_steps(episode.lengths().to(dev), steps, mode, generator, horizon=T)
    else:
        st = step_index.to(dev).long()
        if st.ndim != 2 or st.shape[0] != W or (st.numel() and (int(st.min()) < 0 or int(st.max()) >= T)):
            raise TTError(f"step_index must be (W={W}, K) with values in 0..{T - 1}, got shape {tuple(st.shape)}")
        valid = torch.ones_like(st, dtype=torch.bool)
    K = st.shape[1]
    A = episode.ee_pos.shape[2]
    counts = {len(r.track_link) for r in robots}
    if counts != {A}:
        raise TTError(f"episode has {A} end effectors but the robots have {sorted(counts)} track links")
    tab = _robot_tables(robots)
    used = np.bincount(design, minlength=len(robots)) > 0
    # Every token reads rows (world, step) of the episode: copy those rows once per tensor.
    w_rows = torch.arange(W, device=dev)[:, None].expand(W, K).reshape(-1)
    t_rows = st.reshape(-1)
    rows = w_rows * T + t_rows
    invalid = None
    if not bool(valid.all()):
        invalid = torch.nonzero(~valid.reshape(-1))[:, 0]
    values, ids, mask = {}, {}, {}

    def put(name, v, ent_ok):
        """v (W, K, E, width) -> tokens; ent_ok (W, E) numpy."""
        E = v.shape[2]
        m = valid[:, :, None] & torch.as_tensor(ent_ok, device=dev)[:, None, :]
        values[name] = v.reshape(W, K * E, v.shape[3]).to(dtype)
        ids[name], mask[name] = _token_ids(E, st), m.reshape(W, K * E)

    # Track links and targets: one per end effector.
    if A:
        for name, p, q in (
            ("track_link_obs", episode.ee_pos, episode.ee_quat),
            ("target_pose", episode.target_pos, episode.target_quat),
        ):
            pos = _step_rows(p, rows, w_rows, t_rows).view(W, K, A, 3)
            rot = _quat_to_mat(_step_rows(q, rows, w_rows, t_rows).view(W, K, A, 4)).reshape(W, K, A, 9)
            v = torch.cat([pos, rot], -1)
            if invalid is not None:
                v.masked_fill_(~valid[:, :, None, None], 0.0)
            put(name, v, np.ones((W, A), dtype=bool))

    F, D, B, nA = (tab[f].shape[1] for f in ("free_qposadr", "dyna_qposadr", "ball_qposadr", "actuator_mj"))
    names = (
        (("qpos",) if F or D or B else ())
        + (("qvel",) if D or B else ())
        + (("act_vel", "act_force", "action") if nA else ())
    )
    if not names:
        return TokenBatch(values, ids, mask)
    buf, start, zero = _step_buffer(episode, names, rows, w_rows, t_rows, invalid)
    buf = buf.view(W, K, buf.shape[1])
    width = {n: int(np.prod(getattr(episode, n).shape[2:])) for n in names}

    def gather(cols):
        """Buffer columns (R, E, width) of each robot -> values (W, K, E, width)."""
        E, n = cols.shape[1], cols.shape[2]
        idx = torch.as_tensor(cols[design].reshape(W, 1, E * n), device=dev).expand(W, K, E * n)
        return buf.gather(2, idx).view(W, K, E, n)

    def cols(field, source, n):
        return _columns(tab[field], n, start[source], width[source], zero, field, source, used)

    # Free links: body pose from the free joint's qpos, then the link's offset in the body.
    if F:
        ok = tab["free_qposadr"] >= 0
        raw = gather(cols("free_qposadr", "qpos", 7)).to(episode.qpos.dtype)  # (W, K, F, 7)
        rb = _quat_to_mat(raw[..., 3:])
        orr = torch.as_tensor(tab["free_offset_rot"][design], device=dev).to(rb.dtype)[:, None]
        opp = torch.as_tensor(tab["free_offset_pos"][design], device=dev).to(rb.dtype)[:, None]
        rot = rb @ orr
        pos = (rb @ opp[..., None])[..., 0] + raw[..., :3]
        v = torch.cat([pos, rot.reshape(W, K, F, 9)], -1)
        m = valid[:, :, None] & torch.as_tensor(ok[design], device=dev)[:, None, :]
        v.masked_fill_(~m[..., None], 0.0)
        put("free_link_obs", v, ok[design])

    # Hinge / slide joints.
    if D:
        c = np.concatenate([cols("dyna_qposadr", "qpos", 1), cols("dyna_dofadr", "qvel", 1)], -1)
        put("dyna_joint_obs", gather(c), (tab["dyna_qposadr"] >= 0)[design])

    # Ball joints: quaternion with w >= 0 (q and -q are the same rotation), local angular velocity.
    if B:
        v = gather(np.concatenate([cols("ball_qposadr", "qpos", 4), cols("ball_dofadr", "qvel", 3)], -1))
        quat = v[..., :4]
        v[..., :4] = torch.where(quat[..., :1] < 0, -quat, quat)
        put("ball_joint_obs", v, (tab["ball_qposadr"] >= 0)[design])

    # Actuators: observation and the clean command.
    if nA:
        ok = (tab["actuator_mj"] >= 0)[design]
        put(
            "actuator_obs",
            gather(np.concatenate([cols("actuator_mj", "act_vel", 1), cols("actuator_mj", "act_force", 1)], -1)),
            ok,
        )
        put("control", gather(cols("actuator_mj", "action", 1)), ok)

    return TokenBatch(values, ids, mask)
