"""Warp functions whose source tt writes for one sparsity pattern or topology.

Where a function's arithmetic follows an index list (the entries of a tree-sparse
factorisation, say), tt writes each step as a line of Python with the indices as literals
and compiles that text as a Warp function. The alternative, a loop over the list with
``wp.static(LIST[n][0])`` indices, makes Warp's module hash run the whole code generation
in Python on every process start (Warp cannot hash an expression that depends on a loop
variable without unrolling the loop), about a second per fused rollout module. Text with
literal indices is hashed as text.

The source is registered in `linecache` under a name derived from its content, as Warp
(and `inspect`) read a function's source from there; the same text always gives the same
name, so a module's hash, and its entry in the kernel cache, are stable across processes.
"""

import hashlib
import linecache

import warp as wp


def generated_func(name: str, source: str, namespace: dict, *, module: str) -> wp.Function:
    """The Warp function `name` defined by `source` (a ``def name(...)`` block).

    namespace: the names the source refers to (types in its annotations, ``wp``, other
        Warp functions); they become the function's globals.
    module: the Python module the function belongs to (its Warp module, where Warp files
        functions by name).
    """
    digest = hashlib.sha256(source.encode()).hexdigest()[:16]
    filename = f"<tt generated {module}.{name} {digest}>"
    # mtime None: `linecache.checkcache` keeps the entry (there is no file to check).
    linecache.cache[filename] = (len(source), None, source.splitlines(keepends=True), filename)
    scope = {"__name__": module, "wp": wp, **namespace}
    exec(compile(source, filename, "exec"), scope)
    func = scope.get(name)
    if not callable(func):
        raise ValueError(f"the generated source defines no function {name!r}")
    return wp.func(func)


__all__ = ["generated_func"]
