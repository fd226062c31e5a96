"""Tokens -> a design's choices, for tt's own design spaces.

Works for any `DesignSpace` without knowing its grammar: a design is found whose tokens
match the given ones.

1. Every discrete choice combination of the space is built once at the middle of its
   continuous bounds and tokenized (`CandidateTable`, reusable across calls).
2. Each candidate's token *structure* (token counts per type and every binary attribute:
   geometry and joint types, link IDs, track / free IDs, the joints actuators drive) is
   compared with the target's: per token type, the edit distance of the two token
   sequences, where a substituted token costs the binary attributes that differ and a
   missing or extra token all its attributes + 1 (so a sample that drops one token early
   in a sequence costs that token, not every later one). Only candidates at
   the smallest distance are kept; by default that distance must be 0 (the target's own
   structure). With ``max_distance=None`` a token set no choice matches exactly, as a
   generative model's samples often are (one wrong link-ID bit suffices), is projected
   onto the nearest structure the space has, the way continuous values are clipped to
   their bounds.
3. The rest are ranked by how far their continuous token values are from the target's
   (over the tokens the alignment pairs, each value scaled by its spread over the
   candidates); for the best few, the continuous choices are fitted by
   bounded least squares on those values (each evaluation builds the MJCF, compiles and
   tokenizes it). The first fit whose residual is below `tol` wins; otherwise the lowest
   residual. By default (``fit="chord"``) the fit starts from the candidate's
   linearization at the middle of its bounds, computed once and kept in the table, and
   takes chord steps with Broyden updates, one model build each; a fit that comes near an
   exact one is polished by least squares. With ``fit="least_squares"`` (the reference)
   scipy's solver starts from the middle: exact structures take finite-difference Jacobians
   at every step; projected ones, whose loose tolerances stop after a few steps, take one
   and update it (Broyden), which cuts a typical sample's model builds by ~40 % (178 -> 107)
   at the same residual. On the shipped model's samples the chord fit needs a sixth or less of
   least squares' builds at residuals within 0.3 % (benchmarks/results/decode.md).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from tt.kernels.errors import TTError
from tt.sim.designs import Design, DesignSpace
from tt.tokens.batch import TokenBatch
from tt.tokens.schema import EMBODIMENT_TYPES, SCHEMA, Encoding
from tt.tokens.tokenize import TokenizeConfig, TokenizeWarning, tokenize_models

_FLOAT64 = TokenizeConfig(dtype=np.float64)


def _columns(name: str) -> tuple[np.ndarray, np.ndarray]:
    """Binary and continuous value columns of a token type."""
    t = SCHEMA[name]
    binary, cont = [], []
    for a in t.attributes:
        sl = t.slice(a.name)
        idx = list(range(sl.start, sl.stop))
        if a.encoding is Encoding.BINARY:
            binary += idx
        elif a.encoding is Encoding.SIGNED_LOG:
            binary += idx[1::2]
            cont += idx[0::2]
        else:
            cont += idx
    return np.array(binary, dtype=np.int64), np.array(cont, dtype=np.int64)


def _type_features(tokens: TokenBatch, i: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Sample i's embodiment tokens per type: (binary bits (n, nb) rounded to 0/1, continuous
    values (n, nc)), n its unpadded token count (0 for a type the batch lacks)."""
    out = {}
    for name in EMBODIMENT_TYPES:
        b, c = _columns(name)
        if name not in tokens.values:
            out[name] = (np.zeros((0, len(b)), np.int8), np.zeros((0, len(c))))
            continue
        m = np.asarray(tokens.mask[name][i], dtype=bool)
        v = np.asarray(tokens.values[name][i], dtype=np.float64)[m]
        out[name] = (np.rint(np.clip(v[:, b], 0, 1)).astype(np.int8), v[:, c])
    return out


def _stack(
    feats: list[dict[str, tuple[np.ndarray, np.ndarray]]],
) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per type: (counts (C,), bits (C, P, nb), continuous (C, P, nc)), padded with zeros to
    the largest count P."""
    out = {}
    for name in EMBODIMENT_TYPES:
        counts = np.array([len(f[name][0]) for f in feats], dtype=np.int64)
        P = int(counts.max(initial=0))
        nb, nc = feats[0][name][0].shape[1], feats[0][name][1].shape[1]
        bits = np.zeros((len(feats), P, nb), np.int8)
        cont = np.zeros((len(feats), P, nc))
        for k, f in enumerate(feats):
            bits[k, : counts[k]], cont[k, : counts[k]] = f[name]
        out[name] = (counts, bits, cont)
    return out


def _edit_distances(sb: np.ndarray, bits: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Edit distance of one token sequence to each candidate's, (C,): substituting a token
    costs the binary attributes that differ, inserting or deleting one costs its attributes
    + 1. Vectorised over candidates; sb (n, nb), bits (C, P, nb), counts (C,)."""
    n, (C, P, nb) = len(sb), bits.shape
    gap = nb + 1
    sub = np.abs(bits[:, None, :, :] - sb[None, :, None, :]).sum(-1, dtype=np.int64)  # (C, n, P)
    prev = np.broadcast_to(np.arange(P + 1, dtype=np.int64) * gap, (C, P + 1)).copy()
    for i in range(1, n + 1):
        row = np.empty_like(prev)
        row[:, 0] = i * gap
        diag = prev[:, :-1] + sub[:, i - 1]
        up = prev[:, 1:] + gap
        best = np.minimum(diag, up)
        for j in range(1, P + 1):  # the left move chains along the row
            row[:, j] = np.minimum(best[:, j - 1], row[:, j - 1] + gap)
        prev = row
    return prev[np.arange(C), counts]


def _alignment(sb: np.ndarray, cb: np.ndarray, tie: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Token pairs (sample rows, candidate rows) that an optimal `_edit_distances` alignment
    of sb (n, nb) with cb (c, nb) substitutes; equal lengths and bits give the identity.

    tie: (n, c) cost of pairing two tokens that breaks ties between alignments of equal
    edit distance (which token is the missing one when the bits cannot tell).
    """
    n, c = len(sb), len(cb)
    gap = sb.shape[1] + 1
    sub = np.abs(cb[None, :, :].astype(np.int64) - sb[:, None, :]).sum(-1)  # (n, c)
    # Lexicographic costs (edit distance, then tie cost); gaps add no tie cost.
    D = np.zeros((n + 1, c + 1), np.int64)
    E = np.zeros((n + 1, c + 1))
    D[:, 0] = np.arange(n + 1) * gap
    D[0, :] = np.arange(c + 1) * gap
    move = np.zeros((n + 1, c + 1), np.int8)  # 0 pair, 1 sample token unmatched, 2 candidate token unmatched
    move[1:, 0], move[0, 1:] = 1, 2
    for i in range(1, n + 1):
        for j in range(1, c + 1):
            options = (
                (D[i - 1, j - 1] + sub[i - 1, j - 1], E[i - 1, j - 1] + tie[i - 1, j - 1], 0),
                (D[i - 1, j] + gap, E[i - 1, j], 1),
                (D[i, j - 1] + gap, E[i, j - 1], 2),
            )
            D[i, j], E[i, j], move[i, j] = min(options)
    rows, cols = [], []
    i, j = n, c
    while i > 0 and j > 0:
        if move[i, j] == 0:
            rows.append(i - 1)
            cols.append(j - 1)
            i, j = i - 1, j - 1
        elif move[i, j] == 1:
            i -= 1
        else:
            j -= 1
    return np.array(rows[::-1], np.int64), np.array(cols[::-1], np.int64)


def discrete_choices(space: DesignSpace, limit: int = 20000) -> list[tuple[int, ...]]:
    """Every complete tuple of discrete choices of `space` (depth-first, in option order).

    Raises ValueError if there are more than `limit` (the exhaustive search would be slow).
    """
    out: list[tuple[int, ...]] = []
    stack: list[tuple[int, ...]] = [()]
    while stack:
        prefix = stack.pop()
        params = space.discrete_params(prefix)
        if len(prefix) == len(params):
            out.append(prefix)
            if len(out) > limit:
                raise TTError(
                    f"space {space.name!r} has more than {limit} discrete combinations; raise `limit` to "
                    "search them all"
                )
            continue
        for o in reversed(range(len(params[len(prefix)].options))):
            stack.append(prefix + (o,))
    return out


def _middle(space: DesignSpace, discrete: tuple[int, ...]) -> Design:
    return Design(space.name, discrete, tuple(0.5 * (p.low + p.high) for p in space.continuous_params(discrete)))


class CandidateTable:
    """Tokens of every discrete combination of a space at its continuous midpoint.

    Building it compiles one model per combination (ViperX: 1,404, ~5 ms each); keep the
    table to decode many token sets of the same space.
    """

    def __init__(
        self, space: DesignSpace, limit: int = 20000, batch: int = 256, discrete: list[tuple[int, ...]] | None = None
    ):
        """discrete: only these combinations (default: all of them, at most `limit`)."""
        self.space = space
        self.discrete = (
            [tuple(int(i) for i in d) for d in discrete] if discrete is not None else discrete_choices(space, limit)
        )
        self._linear: dict[int, tuple] = {}  # candidate -> `linearization`, computed on first use
        feats = []
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", TokenizeWarning)
            for start in range(0, len(self.discrete), batch):
                chunk = self.discrete[start : start + batch]
                emb = tokenize_models([space.model(_middle(space, d)) for d in chunk])
                feats += [_type_features(emb.tokens, i) for i in range(len(chunk))]
        self.features = _stack(feats)
        # Candidates that share a token structure share alignments (ViperX: 1,404 choices, 24 structures).
        keys = [
            b"".join(
                np.ascontiguousarray(self.features[n][1][k, : self.features[n][0][k]]).tobytes() + b"|"
                for n in EMBODIMENT_TYPES
            )
            for k in range(len(self.discrete))
        ]
        first: dict[bytes, int] = {}
        representative = []  # the first candidate of each structure
        for k, key in enumerate(keys):
            if key not in first:
                first[key] = len(first)
                representative.append(k)
        self.structure = np.array([first[key] for key in keys], dtype=np.int64)
        self._representative = np.array(representative, dtype=np.int64)
        # Ranking weights of the continuous columns: 1 / variance over the candidates' real
        # tokens, so the values that tell discrete choices apart (a mount's rotation) count
        # as much as large ones that do not (masses); columns no choice changes get 0
        # (their spread over the table is float rounding, not information).
        self.weights = {}
        for n in EMBODIMENT_TYPES:
            counts, _, cont = self.features[n]
            real = cont[np.arange(cont.shape[1])[None, :] < counts[:, None]]
            var = real.var(axis=0) if len(real) else np.zeros(cont.shape[2])
            self.weights[n] = np.where(var > 1e-6, 1.0 / np.maximum(var, 1e-6), 0.0)  # below: float rounding

    def __len__(self) -> int:
        return len(self.discrete)

    def distances(self, feat: dict[str, tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        """Structure distance of one token set to every candidate, (C,): per token type, the
        edit distance of the token sequences (`_edit_distances`: a token whose binary
        attributes differ costs how many differ, a missing or extra token its attributes
        + 1), summed over types. 0 means the same token structure; a sample that misses one
        token early in a sequence costs that one token, not every later one."""
        # One edit distance per distinct structure, shared by its candidates.
        reps = self._representative
        per_structure = np.zeros(len(reps), np.int64)
        for name in EMBODIMENT_TYPES:
            counts, bits, _ = self.features[name]
            per_structure += _edit_distances(feat[name][0], bits[reps], counts[reps])
        return per_structure[self.structure]

    def alignment(
        self, feat: dict[str, tuple[np.ndarray, np.ndarray]], i: int
    ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Per type, the (sample rows, candidate rows) token pairs of candidate i's optimal
        alignment, the same for every candidate of its structure (`self.structure`): among
        alignments of equal edit distance, the one whose paired tokens' continuous values
        are closest (weighted, `self.weights`) to the structure's mean candidate."""
        same = self.structure == self.structure[i]
        out = {}
        for name in EMBODIMENT_TYPES:
            counts, bits, cont = self.features[name]
            mean = cont[same, : counts[i]].mean(axis=0)
            tie = (self.weights[name] * (feat[name][1][:, None, :] - mean[None, :, :]) ** 2).sum(-1)
            out[name] = _alignment(feat[name][0], bits[i, : counts[i]], tie)
        return out

    def linearization(self, i: int) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Candidate i's continuous token values at the middle of its continuous bounds and
        their slopes there: (values {type: (n, nc)}, slopes {type: (n, nc, p)}), n the
        candidate's own token count; forward differences in float64, p + 1 model builds the
        first time, kept for later calls. A choice whose step changes the token structure
        gets slope 0."""
        if i not in self._linear:
            params = self.space.continuous_params(self.discrete[i])
            lo, hi = np.array([q.low for q in params]), np.array([q.high for q in params])
            x = 0.5 * (lo + hi)
            h = 1e-5 * np.maximum(hi - lo, 1e-9)
            X = np.vstack([x[None], x[None] + np.diag(h)])
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", TokenizeWarning)
                emb = tokenize_models(
                    [
                        self.space.model(Design(self.space.name, self.discrete[i], tuple(float(v) for v in row)))
                        for row in X
                    ],
                    _FLOAT64,
                )
            feats = [_type_features(emb.tokens, k) for k in range(len(X))]
            base = feats[0]
            same = [all(np.array_equal(f[n][0], base[n][0]) for n in EMBODIMENT_TYPES) for f in feats[1:]]
            values = {n: base[n][1] for n in EMBODIMENT_TYPES}
            slopes = {
                n: np.stack(
                    [
                        (f[n][1] - base[n][1]) / h[j] if ok else np.zeros_like(base[n][1])
                        for j, (f, ok) in enumerate(zip(feats[1:], same))
                    ],
                    -1,
                )
                if len(h)
                else np.zeros(base[n][1].shape + (0,))
                for n in EMBODIMENT_TYPES
            }
            self._linear[i] = (values, slopes)
        return self._linear[i]

    def continuous_error(
        self,
        feat: dict[str, tuple[np.ndarray, np.ndarray]],
        candidates: np.ndarray,
        pairs: dict[str, tuple[np.ndarray, np.ndarray]],
    ) -> np.ndarray:
        """Weighted sum of squared differences of the continuous values of the aligned tokens
        (`self.weights`), (K,) for K candidates of one structure (`pairs`, its alignment)."""
        out = np.zeros(len(candidates))
        for n, (r, c) in pairs.items():
            diff = self.features[n][2][candidates[:, None], c[None, :]] - feat[n][1][r][None]  # (K, pairs, nc)
            out += (self.weights[n] * diff**2).sum(axis=(1, 2))
        return out


@dataclass
class DesignFit:
    """Result of `design_from_tokens`.

    design: the best design found (None when no discrete combination is within
    `max_distance` of the target's token structure); residual: RMS difference of the
    continuous token values (of the aligned tokens) at the fit; candidates: discrete
    combinations at the smallest structure distance; fitted: how many of them had their
    continuous choices fitted; distance: that structure distance (0: the target's own
    structure; see `CandidateTable.distances`).
    """

    design: Design | None
    residual: float
    candidates: int
    fitted: int
    distance: int = 0

    @property
    def exact(self) -> bool:
        return self.design is not None and self.distance == 0 and self.residual < 1e-4


class _BroydenJacobian:
    """The Jacobian of `residuals` for least squares: forward differences (stepping inward
    at an upper bound, all perturbed designs tokenized together) at the first iterate, then
    Broyden's rank-one update from each accepted step's change in residuals; with
    ``update=False``, forward differences at every iterate. The residual at an iterate is
    the one the solver just evaluated there (`fun`), not evaluated again.

    A projected target has no exact fit, and its loose tolerances stop the solver after a
    few steps, so one finite-difference Jacobian (p model builds) and an update per step
    replace p builds per step: the builds are most of a decode's time. Exact structures
    keep finite differences at every step (`design_from_tokens`), as they fit to 1e-10.
    """

    def __init__(self, residuals, hi: np.ndarray, seen: dict[bytes, np.ndarray] | None = None, update: bool = True):
        self.residuals, self.hi, self.update = residuals, hi, update
        self.seen: dict[bytes, np.ndarray] = dict(seen or {})
        self.x = self.r = self.J = None
        self.refresh = True

    def fun(self, x: np.ndarray) -> np.ndarray:
        r = self.residuals(x[None])[0]
        self.seen[x.tobytes()] = r
        return r

    def __call__(self, x: np.ndarray) -> np.ndarray:
        r = self.seen.get(x.tobytes())
        if r is None:
            r = self.fun(x)
        # A structure change (residual 1e3) is a jump, not a slope: take fresh differences,
        # and again at the next step when a difference itself crossed one.
        if not self.update or self.refresh or bool(np.any(r >= 1e3)) or bool(np.any(self.r >= 1e3)):
            h = 1e-6 * np.maximum(1.0, np.abs(x))
            h = np.where(x + h > self.hi, -h, h)
            R = self.residuals(x[None] + np.diag(h))
            self.J = ((R - r) / h[:, None]).T
            self.refresh = bool(np.any(R >= 1e3))
        else:
            dx, dr = x - self.x, r - self.r
            step = float(dx @ dx)
            if step > 0:
                self.J = self.J + np.outer(dr - self.J @ dx, dx) / step
        self.x, self.r = x.copy(), r
        return self.J


def _chord_fit(
    residuals,
    f0: np.ndarray,
    J: np.ndarray,
    x0: np.ndarray,
    target: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    iterations: int,
    ftol: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Bounded least squares of the token residuals from a linearization (the chord method,
    with Broyden's updates), one model build per step.

    f0 (m,), J (m, p): the candidate's aligned continuous token values at x0 and their slopes
    there (`CandidateTable.linearization`). The linear model's bounded minimiser is the first
    iterate; each further step solves the linear model at the true residual (`residuals`),
    halving once when it does not lower the residual, and updates the slopes from the step
    (Broyden). It stops when a step fails or gains less than `ftol` of the residual's norm,
    or after `iterations` steps; where the slopes drift from the true ones that can be a
    little above what least squares reaches (`design_from_tokens`). Returns (x (p,),
    residuals at x (m,)).
    """
    from scipy.optimize import lsq_linear

    def solve(rhs: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
        return lsq_linear(J, rhs, bounds=(lower, np.maximum(upper, lower + 1e-15)), lsq_solver="exact").x

    x, r = x0, f0 - target
    first = np.clip(solve(target - f0 + J @ x0, lo, hi), lo, hi)
    r_first = residuals(first[None])[0]
    if np.linalg.norm(r_first) < np.linalg.norm(r):
        x, r = first, r_first
    for _ in range(iterations):
        dx = solve(-r, lo - x, hi - x)
        for scale in (1.0, 0.5):
            x_new = np.clip(x + scale * dx, lo, hi)
            r_new = residuals(x_new[None])[0]
            if np.linalg.norm(r_new) < np.linalg.norm(r):
                break
        else:
            break
        gain = np.linalg.norm(r) - np.linalg.norm(r_new)
        step = x_new - x
        J = J + np.outer(r_new - r - J @ step, step) / float(step @ step)
        x, r = x_new, r_new
        if gain < ftol * np.linalg.norm(r):
            break
    return x, r


#: How `design_from_tokens` fits the continuous choices.
FITS = ("chord", "least_squares")

#: A chord fit whose RMS token residual is below this (but above the tolerance) is polished
#: by least squares: it is the token set of some design, which should be found to `tol`.
POLISH_BELOW = 1e-3

#: The chord fit's steps at most, and the relative gain in the residual's norm below which
#: it stops.
CHORD_STEPS, CHORD_FTOL = 20, 1e-4


def design_from_tokens(
    tokens: TokenBatch,
    index: int,
    space: DesignSpace,
    *,
    table: CandidateTable | None = None,
    top_k: int = 6,
    tol: float = 1e-5,
    max_distance: int | None = 0,
    broyden: bool | None = None,
    fit: str = "chord",
) -> DesignFit:
    """The design of `space` whose tokens best match sample `index` of `tokens` (see module).

    max_distance: the largest structure distance (`CandidateTable.distances`) to the nearest
    discrete choice that is accepted: 0 asks for the exact token structure, None projects
    any token set onto the nearest structure of the space. broyden: Broyden-updated
    Jacobians in the continuous fit (`_BroydenJacobian`) instead of finite differences at
    every step; None: for projected structures only. fit: "chord" (default) starts from the
    candidate's linearization, kept in the table (`CandidateTable.linearization`), and takes
    chord steps (`_chord_fit`), a few model builds per candidate; a fit that it leaves below
    `POLISH_BELOW` goes on with "least_squares" from there. "least_squares": scipy's
    trust-region least squares from the middle of the bounds, the reference.
    """
    from scipy.optimize import least_squares

    if max_distance is not None and max_distance < 0:
        raise TTError(f"max_distance must be >= 0 or None, got {max_distance}")
    if fit not in FITS:
        raise TTError(f"fit = {fit!r}; valid: {list(FITS)}")
    table = table if table is not None and table.space is space else CandidateTable(space)
    feat = _type_features(tokens, index)
    if len(table) == 0:
        return DesignFit(None, float("inf"), 0, 0, -1)
    structure = table.distances(feat)
    nearest = int(structure.min())
    if max_distance is not None and nearest > max_distance:
        return DesignFit(None, float("inf"), 0, 0, nearest)
    match = np.flatnonzero(structure == nearest)
    by_structure: dict[int, dict] = {}
    for i in match:
        if int(table.structure[i]) not in by_structure:
            by_structure[int(table.structure[i])] = table.alignment(feat, int(i))
    pairs = {int(i): by_structure[int(table.structure[i])] for i in match}
    error = np.zeros(len(table))
    for k, rows in by_structure.items():
        members = match[table.structure[match] == k]
        error[members] = table.continuous_error(feat, members, rows)
    order = sorted(pairs, key=lambda i: error[i])
    best: tuple[float, Design | None] = (float("inf"), None)
    fitted = 0
    for i in order[:top_k]:
        discrete = table.discrete[i]
        params = space.continuous_params(discrete)
        lo = np.array([p.low for p in params])
        hi = np.array([p.high for p in params])
        own = {n: table.features[n][1][i, : table.features[n][0][i]] for n in EMBODIMENT_TYPES}
        target = np.concatenate([feat[n][1][r].ravel() for n, (r, _) in pairs[i].items()])

        def residuals(X: np.ndarray, discrete=discrete, own=own, rows=pairs[i], target=target) -> np.ndarray:
            """Token residuals of k continuous choice vectors X (k, p), one tokenizer call."""
            X = np.clip(X, lo, hi)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", TokenizeWarning)
                emb = tokenize_models(
                    [space.model(Design(space.name, discrete, tuple(float(v) for v in x))) for x in X], _FLOAT64
                )
            out = np.empty((len(X), len(target)))
            for k in range(len(X)):
                f = _type_features(emb.tokens, k)
                if any(not np.array_equal(f[n][0], own[n]) for n in EMBODIMENT_TYPES):
                    out[k] = 1e3  # the continuous choices changed the structure
                else:
                    out[k] = np.concatenate([f[n][1][c].ravel() for n, (_, c) in rows.items()]) - target
            return out

        fitted += 1
        if len(params) == 0:
            x = np.zeros(0)
            r = residuals(x[None])[0]
        else:
            # float64 candidate tokens keep finite differences clean; the target's float32
            # rounding (~1e-7 relative) is far below `tol`. A projected target has no exact
            # fit: its residual stalls well above `tol`, so fewer, looser iterations suffice.
            exact = nearest == 0
            x, r = 0.5 * (lo + hi), None
            if fit == "chord":
                values, slopes = table.linearization(int(i))
                rows = pairs[i]
                f0 = np.concatenate([values[n][c].ravel() for n, (_, c) in rows.items()])
                J = np.concatenate([slopes[n][c].reshape(-1, len(params)) for n, (_, c) in rows.items()])
                x, r = _chord_fit(residuals, f0, J, x, target, lo, hi, iterations=CHORD_STEPS, ftol=CHORD_FTOL)
        # The chord's result stands unless it nearly fits (a design's own tokens, to be recovered
        # as exactly as least squares does); a model's sample stalls far above that, where more
        # precision means nothing.
        if len(params) and (r is None or (r.size and np.sqrt(np.mean(r**2)) < POLISH_BELOW)):
            options = dict(
                bounds=(lo, hi),
                x_scale=np.maximum(hi - lo, 1e-9),
                xtol=1e-10 if exact else 1e-4,
                ftol=1e-10 if exact else 1e-4,
                gtol=1e-10 if exact else 1e-6,
                max_nfev=(20 if exact else 5) * (len(params) + 1),
            )
            use_broyden = (not exact) if broyden is None else broyden
            jac = _BroydenJacobian(residuals, hi, update=use_broyden)
            sol = least_squares(jac.fun, x, jac=jac, **options)
            if use_broyden and sol.njev > 1:
                # Again from fresh differences where the updated Jacobian's steps stalled
                # (not needed when the first pass took no step).
                x = np.clip(sol.x, lo, hi)
                jac = _BroydenJacobian(residuals, hi, seen={x.tobytes(): sol.fun})
                sol = least_squares(jac.fun, x, jac=jac, **options)
            x, r = np.clip(sol.x, lo, hi), sol.fun
        rms = float(np.sqrt(np.mean(r**2))) if r.size else 0.0
        if rms < best[0]:
            best = (rms, Design(space.name, discrete, tuple(float(v) for v in x)))
        if rms < tol:
            break
    return DesignFit(best[1], best[0], len(match), fitted, nearest)
