"""The installed tt version, recorded in the files tt writes (datasets, checkpoints)."""

from importlib.metadata import PackageNotFoundError, version


def tt_version() -> str:
    """The version of the installed ``tt`` distribution; "0.0.0" in a source tree that was not installed."""
    try:
        return version("tt")
    except PackageNotFoundError:
        return "0.0.0"
