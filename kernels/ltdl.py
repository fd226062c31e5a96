"""Tree-ordered L^T D L factorisation of symmetric positive definite matrices (Warp).

A joint-space mass matrix of a kinematic tree has M[i, j] = 0 unless dof j is dof i or one
of its ancestors. Factoring M = L^T D L from the last dof to the first (MuJoCo's
`mj_factorI`) keeps that pattern: no fill-in, so a two-arm robot costs about half a dense
factorisation. A dense matrix is the same algorithm on a chain (every dof the parent of
the next). The index lists are computed in Python and compiled in, so the generated code
is straight-line arithmetic on thread-local matrices.
"""

import functools
from types import SimpleNamespace

import warp as wp


def ltdl_ops(parent: tuple[int, ...]):
    """Static index lists of the factorisation and solve for dof parents `parent` (-1: root).

    factor: (k, i, j, first) in execution order: when `first`, L[k, i] = A[k, i] / A[k, k];
        then A[i, j] -= L[k, i] A[k, j] (j = i and its ancestors).
    solve_up: (k, i), k descending: x[i] -= L[k, i] x[k].
    solve_down: (i, j), i ascending: x[i] -= L[i, j] x[j].
    pairs: (i, j) with j = i or an ancestor of i: the structurally nonzero lower triangle.
    """
    n = len(parent)

    def ancestors(d):
        out = []
        d = parent[d]
        while d >= 0:
            out.append(d)
            d = parent[d]
        return out

    for d in range(n):
        if not -1 <= parent[d] < d:
            raise ValueError(f"parent[{d}] = {parent[d]}; dof parents must precede their children")
    factor = []
    for k in reversed(range(n)):
        for i in ancestors(k):
            for m, j in enumerate([i] + ancestors(i)):
                factor.append((k, i, j, m == 0))
    solve_up = [(k, i) for k in reversed(range(n)) for i in ancestors(k)]
    solve_down = [(i, j) for i in range(n) for j in reversed(ancestors(i))]
    pairs = [(i, j) for i in range(n) for j in [i] + ancestors(i)]
    return tuple(factor), tuple(solve_up), tuple(solve_down), tuple(pairs)


@functools.cache
def ltdl_funcs(parent: tuple[int, ...], mat_type: type, vec_type: type) -> SimpleNamespace:
    """factor(A) -> (L, D) and solve(L, D, b) -> A^-1 b for the sparsity of `parent`.

    A: (n, n) `mat_type`, only its lower triangle on the tree pattern is read; L holds the
    strict lower factor, D (n,) `vec_type` the diagonal.
    """
    FACTOR, SOLVE_UP, SOLVE_DOWN, _ = ltdl_ops(parent)
    N = len(parent)

    @wp.func
    def factor(A: mat_type):
        L = mat_type()
        for n in range(wp.static(len(FACTOR))):
            k = wp.static(FACTOR[n][0])
            i = wp.static(FACTOR[n][1])
            j = wp.static(FACTOR[n][2])
            if wp.static(FACTOR[n][3]):
                L[k, i] = A[k, i] / A[k, k]
            A[i, j] = A[i, j] - L[k, i] * A[k, j]
        D = vec_type()
        for d in range(N):
            D[d] = A[d, d]
        return L, D

    @wp.func
    def solve(L: mat_type, D: vec_type, x: vec_type):
        # x arrives as b and is overwritten with the solution (no alias: see dynamics.py).
        for n in range(wp.static(len(SOLVE_UP))):
            k = wp.static(SOLVE_UP[n][0])
            i = wp.static(SOLVE_UP[n][1])
            x[i] = x[i] - L[k, i] * x[k]
        for d in range(N):
            x[d] = x[d] / D[d]
        for n in range(wp.static(len(SOLVE_DOWN))):
            i = wp.static(SOLVE_DOWN[n][0])
            j = wp.static(SOLVE_DOWN[n][1])
            x[i] = x[i] - L[i, j] * x[j]
        return x

    return SimpleNamespace(factor=factor, solve=solve)


def chain(n: int) -> tuple[int, ...]:
    """Parents of a chain of n dofs: the pattern of a dense matrix."""
    return tuple(range(-1, n - 1))
