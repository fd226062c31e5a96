"""The pinned simulator stack imports together at the versions constraints.txt names."""

from importlib.metadata import version
from pathlib import Path


def _pins() -> dict[str, str]:
    pins = {}
    for line in (Path(__file__).parents[1] / "constraints.txt").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if "==" in line:
            name, v = line.split("==")
            pins[name.strip()] = v.strip()
    return pins


def test_simulator_stack_imports_together_at_pinned_versions():
    import cma  # noqa: F401
    import meshcat  # noqa: F401
    import mink  # noqa: F401
    import mujoco
    import mujoco_warp  # noqa: F401
    import newton  # noqa: F401
    import torch
    import warp as wp

    pins = _pins()
    for name in ("torch", "warp-lang", "newton", "mujoco", "mujoco-warp", "mink", "meshcat", "cma"):
        assert version(name).split("+")[0] == pins[name], f"{name} {version(name)} != pinned {pins[name]}"
    # newton 1.8 declares mujoco~=3.17 and mujoco-warp~=3.17: the pins must agree with it.
    assert mujoco.__version__.startswith("3.17") and version("mujoco-warp").startswith("3.17")
    assert torch.__version__.startswith("2.13")
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    assert "cpu" in [str(d) for d in wp.get_devices()]
