"""tt: motion-conditioned robot co-design.

The common path in Python (`tt.api`; each name loads its modules on first use, so
``import tt`` stays fast)::

    import tt

    toss = tt.motion("toss")                        # a library name or a motion file
    best = tt.optimize("viperx", [toss], "tracking", method="cmaes", budget=60, seed=0)
    check = tt.validate([best.best], [toss])        # the oracle: MuJoCo C + mink
    tt.view([best.best], motion=toss, html="best.html")

`get_space`, `motion` (`load_motion`), `save_motion`, `rollout`, `validate`, `optimize`,
`predict`, `generate_dataset`, `dataset_info`, `train`, `tokenize`, `detokenize` and `view`
are documented in `tt.api`; the CLI (``tt ...``) calls the same library functions.

The implementation lives in the subpackages, layered high -> low: the app (`tt.api`,
`tt.cli`, `tt.demo`, `tt.report`, `tt.generate`, `tt.optimizers`) > `tt.viz` > `tt.guidance`
> `tt.baselines` > `tt.dit` > `tt.tokens` > `tt.sim` > `tt.kernels`; imports only go down.
"""

#: The API's names, each loaded from `tt.api` on first use.
_API = (
    "get_space",
    "motion",
    "load_motion",
    "save_motion",
    "rollout",
    "validate",
    "optimize",
    "predict",
    "generate_dataset",
    "dataset_info",
    "train",
    "tokenize",
    "detokenize",
    "view",
)

__all__ = ["TTError", "__version__", *_API]


def __getattr__(name: str):
    # Lazy, like the API: tt.kernels (whose package imports Warp and MuJoCo) loads on first use.
    if name == "TTError":
        from tt.kernels.errors import TTError as value
    elif name == "__version__":
        from importlib.metadata import PackageNotFoundError, version

        try:
            value = version("tt")
        except PackageNotFoundError:
            value = "0.0.0"  # a source tree that was not installed, as tt.kernels.version.tt_version says
    elif name in _API:
        from tt import api

        value = getattr(api, name)
    else:
        raise AttributeError(f"module 'tt' has no attribute {name!r}")
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API))
