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

from tt.kernels.generated import generated_func


def ltdl_ops(parent: tuple[int, ...]):
    """Static index lists of the factorisation and solve for dof parents `parent` (-1: root).

    factor: (k, i, j, first) in execution order: when `first`, L[k, i] = A[k, i] / A[k, k];
        then A[i, j] -= L[k, i] A[k, j] (j = i and its ancestors).
    solve_up: (k, i), k descending: x[i] -= L[k, i] x[k].
    solve_down: (i, j), i ascending: x[i] -= L[i, j] x[j].
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
    return tuple(factor), tuple(solve_up), tuple(solve_down)


@functools.cache
def ltdl_funcs(parent: tuple[int, ...], mat_type: type, vec_type: type) -> SimpleNamespace:
    """factor(A) -> (L, D) and solve(L, D, b) -> A^-1 b for the sparsity of `parent`.

    A: (n, n) `mat_type`, only its lower triangle on the tree pattern is read; L holds the
    strict lower factor, D (n,) `vec_type` the diagonal. Both are written out step by step
    with literal indices (`tt.kernels.generated`).
    """
    factor_ops, solve_up, solve_down = ltdl_ops(parent)
    n = len(parent)
    factor = ["def factor(A: mat_type):", "    L = mat_type()"]
    for k, i, j, first in factor_ops:
        if first:
            factor.append(f"    L[{k}, {i}] = A[{k}, {i}] / A[{k}, {k}]")
        factor.append(f"    A[{i}, {j}] = A[{i}, {j}] - L[{k}, {i}] * A[{k}, {j}]")
    factor.append("    D = vec_type()")
    factor += [f"    D[{d}] = A[{d}, {d}]" for d in range(n)]
    factor.append("    return L, D")
    # x arrives as b and is overwritten with the solution (no alias: see dynamics.py).
    solve = ["def solve(L: mat_type, D: vec_type, x: vec_type):"]
    solve += [f"    x[{i}] = x[{i}] - L[{k}, {i}] * x[{k}]" for k, i in solve_up]
    solve += [f"    x[{d}] = x[{d}] / D[{d}]" for d in range(n)]
    solve += [f"    x[{i}] = x[{i}] - L[{i}, {j}] * x[{j}]" for i, j in solve_down]
    solve.append("    return x")
    names = {"mat_type": mat_type, "vec_type": vec_type}
    return SimpleNamespace(
        factor=generated_func("factor", "\n".join(factor) + "\n", names, module=__name__),
        solve=generated_func("solve", "\n".join(solve) + "\n", names, module=__name__),
    )


def chain(n: int) -> tuple[int, ...]:
    """Parents of a chain of n dofs: the pattern of a dense matrix."""
    return tuple(range(-1, n - 1))
