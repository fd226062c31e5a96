"""Device selection: CUDA when present, else the CPU; always an explicit parameter."""

from __future__ import annotations

from tt.kernels.errors import TTError


def default_device() -> str:
    """``"cuda"`` when Warp sees a CUDA device, else ``"cpu"``."""
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    return "cuda" if wp.is_cuda_available() else "cpu"


def resolve_device(device: str | None) -> str:
    """Validate a device name for both Warp and torch; `None` picks `default_device()`."""
    import warp as wp

    if device is None:
        return default_device()
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    names = [str(d) for d in wp.get_devices()]
    aliases = {"cuda": "cuda:0"}
    if aliases.get(device, device) not in names:
        raise TTError(f"device {device!r} does not exist here; available: {names}")
    return device
