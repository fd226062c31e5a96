"""Tokens -> a design's choices, for tt's own design spaces.

Works for any `DesignSpace` without knowing its grammar: a design is found whose tokens
match the given ones.

1. Every discrete choice combination of the space is built once at the middle of its
   continuous bounds and tokenized (`CandidateTable`, reusable across calls).
2. Candidates whose token *structure* differs from the target are dropped: token counts
   per type and every binary attribute (geometry and joint types, link IDs, track / free
   IDs, the joints actuators drive).
3. The rest are ranked by how far their continuous token values are from the target's;
   for the best few, the continuous choices are fitted by bounded least squares on those
   values (each evaluation builds the MJCF, compiles and tokenizes it). The first fit
   whose residual is below `tol` wins; otherwise the lowest residual.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

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


def _features(tokens: TokenBatch, i: int) -> tuple[bytes, np.ndarray]:
    """(structure key, continuous values) of sample i's embodiment tokens."""
    key, cont = [], []
    for name in EMBODIMENT_TYPES:
        if name not in tokens.values:
            key.append(np.array([0]))
            continue
        m = np.asarray(tokens.mask[name][i], dtype=bool)
        v = np.asarray(tokens.values[name][i], dtype=np.float64)[m]
        b, c = _columns(name)
        key += [np.array([len(v)]), np.rint(np.clip(v[:, b], 0, 1)).astype(np.int64).ravel()]
        cont.append(v[:, c].ravel())
    return np.concatenate(key).astype(np.int64).tobytes(), np.concatenate(cont)


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
                raise ValueError(f"space {space.name!r} has more than {limit} discrete combinations; raise `limit` to search them all")
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

    def __init__(self, space: DesignSpace, limit: int = 20000, batch: int = 256, discrete: list[tuple[int, ...]] | None = None):
        """discrete: only these combinations (default: all of them, at most `limit`)."""
        self.space = space
        self.discrete = [tuple(int(i) for i in d) for d in discrete] if discrete is not None else discrete_choices(space, limit)
        self.keys: list[bytes] = []
        self.values: list[np.ndarray] = []
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", TokenizeWarning)
            for start in range(0, len(self.discrete), batch):
                chunk = self.discrete[start:start + batch]
                emb = tokenize_models([space.model(_middle(space, d)) for d in chunk])
                for i in range(len(chunk)):
                    k, v = _features(emb.tokens, i)
                    self.keys.append(k)
                    self.values.append(v)


@dataclass
class DesignFit:
    """Result of `design_from_tokens`.

    design: the best design found (None when no discrete combination has the target's
    token structure); residual: RMS difference of the continuous token values at the fit;
    candidates: discrete combinations with the target's structure; fitted: how many of
    them had their continuous choices fitted.
    """

    design: Design | None
    residual: float
    candidates: int
    fitted: int

    @property
    def exact(self) -> bool:
        return self.design is not None and self.residual < 1e-4


def design_from_tokens(tokens: TokenBatch, index: int, space: DesignSpace, *, table: CandidateTable | None = None,
                       top_k: int = 6, tol: float = 1e-5) -> DesignFit:
    """The design of `space` whose tokens best match sample `index` of `tokens` (see module)."""
    from scipy.optimize import least_squares

    table = table if table is not None and table.space is space else CandidateTable(space)
    key, target = _features(tokens, index)
    match = [i for i, k in enumerate(table.keys) if k == key]
    if not match:
        return DesignFit(None, float("inf"), 0, 0)
    order = sorted(match, key=lambda i: float(np.sum((table.values[i] - target) ** 2)))
    best: tuple[float, Design | None] = (float("inf"), None)
    fitted = 0
    for i in order[:top_k]:
        discrete = table.discrete[i]
        params = space.continuous_params(discrete)
        lo = np.array([p.low for p in params])
        hi = np.array([p.high for p in params])

        def residual(x: np.ndarray, discrete=discrete) -> np.ndarray:
            x = np.clip(x, lo, hi)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", TokenizeWarning)
                emb = tokenize_models([space.model(Design(space.name, discrete, tuple(float(v) for v in x)))], _FLOAT64)
            k, v = _features(emb.tokens, 0)
            return v - target if k == key else np.full_like(target, 1e3)

        fitted += 1
        if len(params) == 0:
            r = residual(np.zeros(0))
            x = np.zeros(0)
        else:
            # float64 candidate tokens keep finite differences clean; the target's float32
            # rounding (~1e-7 relative) is far below `tol`.
            sol = least_squares(residual, 0.5 * (lo + hi), bounds=(lo, hi), x_scale=np.maximum(hi - lo, 1e-9), diff_step=1e-6,
                                xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=20 * (len(params) + 1))
            x, r = np.clip(sol.x, lo, hi), sol.fun
        rms = float(np.sqrt(np.mean(r**2))) if r.size else 0.0
        if rms < best[0]:
            best = (rms, Design(space.name, discrete, tuple(float(v) for v in x)))
        if rms < tol:
            break
    return DesignFit(best[1], best[0], len(match), fitted)

