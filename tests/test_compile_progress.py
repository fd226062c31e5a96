"""A first rollout that has to compile kernels says so and counts them (issue 53).

Warp compiles one module per tree topology on its first use and keeps it in its kernel cache.
A rollout with ``progress=True`` (what the CLI asks for) checks which of its topologies'
modules are neither loaded nor cached (`tt.kernels.rollout.module_built`) and, where some
are, shows a bar counting them on stderr below a one-line note (`tt.sim.rollout.COMPILE_NOTE`).
Each test runs in a subprocess with a fresh cache folder (``WARP_CACHE_PATH``). The default
one compiles a one-, a two- and a three-joint arm on 2 threads (about 55 s on a 2-core CPU at
load 10); the same on one thread (the groups one after another) and ``tt rollout`` on ViperX
are slow.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

#: Two arms of different topologies (one hinge; two hinges), small enough to compile in seconds.
_SCRIPT = textwrap.dedent(
    """
    import sys
    import mujoco
    import numpy as np
    from tt.kernels.model import topology_of
    from tt.kernels.rollout import module_built, rollout_kernels
    from tt.sim.motions.base import Motion
    from tt.sim.rollout import load_rollout_kernels, rollout

    def arm(links):
        bodies, close = "", ""
        for i in range(links):
            bodies += (
                f'<body name="b{i}" pos="{0.1 if i == 0 else 0.2} 0 0">'
                f'<joint name="j{i}" type="hinge" axis="0 0 1" range="-2 2" damping="0.1" armature="0.01"/>'
                '<geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.02" density="1000"/>'
            )
            close += "</body>"
        site = '<site name="ee_0" pos="0.2 0 0"/>'
        acts = "".join(f'<position joint="j{i}" kp="30" kv="2" ctrlrange="-2 2"/>' for i in range(links))
        return mujoco.MjModel.from_xml_string(
            '<mujoco><compiler angle="radian"/><option timestep="0.002"><flag contact="disable"/></option>'
            f"<worldbody>{bodies}{site}{close}</worldbody><actuator>{acts}</actuator></mujoco>"
        )

    models = [arm(1), arm(2)]
    steps = 5
    pos = np.tile([[0.3, 0.05, 0.0]], (steps, 1))[:, None]
    quat = np.tile([[1.0, 0.0, 0.0, 0.0]], (steps, 1))[:, None]
    motion = Motion("hold", pos, quat)
    modules = [rollout_kernels(topology_of(m, ("ee_0",))).module for m in models]
    print("built before:", [module_built(name, "cpu") for name in modules], file=sys.stdout)
    rollout(models, [motion], device="cpu", progress=True, threads=int(sys.argv[1]))
    print("built after:", [module_built(name, "cpu") for name in modules], file=sys.stdout)
    rollout(models, [motion], device="cpu", progress=True, threads=int(sys.argv[1]))
    # What evaluate_designs' preload (large batches) calls: a third topology, and the two loaded.
    third = rollout_kernels(topology_of(arm(3), ("ee_0",))).module
    load_rollout_kernels([third, *modules, third], "cpu", progress=True)
    print("third built:", module_built(third, "cpu"), file=sys.stdout)
    print("done", file=sys.stdout)
    """
)


def _env(cache) -> dict:
    return {**os.environ, "WARP_CACHE_PATH": str(cache)}


@pytest.mark.parametrize("threads", [pytest.param(1, marks=pytest.mark.slow), 2])
def test_first_rollout_shows_a_compile_bar_once(tmp_path, threads):
    """Fresh cache: the note and a bar over 2 topologies on stderr; the modules count as
    built afterwards; a second rollout (loaded) shows nothing; `load_rollout_kernels` (the
    large batches' preload) counts only the one of its three not yet built; a new process
    (all cached) shows nothing."""
    script = tmp_path / "two_arms.py"
    script.write_text(_SCRIPT)
    cache = tmp_path / "warp_cache"
    run = subprocess.run(
        [sys.executable, str(script), str(threads)], env=_env(cache), capture_output=True, text=True, timeout=600
    )
    assert run.returncode == 0, run.stderr[-3000:]
    assert "built before: [False, False]" in run.stdout
    assert "built after: [True, True]" in run.stdout
    assert "compiling Warp kernels for 2 of 2 robot structure(s) on cpu" in run.stderr
    assert "once per structure (topology), then loaded from Warp's kernel cache" in run.stderr
    assert str(cache) in run.stderr
    assert "compiling kernels" in run.stderr and "2/2" in run.stderr
    # Once per compile in the process: the second rollout found both modules loaded; the
    # preload of a third topology beside them counts one.
    assert run.stderr.count("compiling Warp kernels") == 2
    assert "compiling Warp kernels for 1 of 3 robot structure(s)" in run.stderr and "1/1" in run.stderr
    assert "third built: True" in run.stdout and "done" in run.stdout
    again = subprocess.run(
        [sys.executable, str(script), str(threads)], env=_env(cache), capture_output=True, text=True, timeout=600
    )
    assert again.returncode == 0, again.stderr[-3000:]
    assert "built before: [True, True]" in again.stdout
    assert "compiling" not in again.stderr


@pytest.mark.slow
def test_cli_rollout_shows_the_compile_bar(tmp_path):
    """``tt rollout`` on random ViperX designs of 2 topologies with a fresh kernel cache: the
    note and the bar on stderr (minutes: two full ViperX modules compile)."""
    from tt.kernels.model import topology_key
    from tt.sim.designs import get_space, save_designs

    space = get_space("viperx")
    first: dict = {}
    for d in space.sample(64, 0):
        first.setdefault(topology_key(space.model(d), space.ee_sites()), d)
    designs = list(first.values())[:2]
    assert len(designs) == 2
    save_designs(designs, tmp_path / "designs.json")
    _cli_says_it_compiles(["rollout", "--space", "viperx", "--design", str(tmp_path / "designs.json")], tmp_path)


def _cli_says_it_compiles(args: list[str], tmp_path) -> None:
    """``tt ARGS --motion toss`` with a fresh kernel cache succeeds and prints the note and the bar."""
    run = subprocess.run(
        [sys.executable, "-m", "tt.cli", *args, "--motion", "toss"],
        env=_env(tmp_path / "warp_cache"),
        capture_output=True,
        text=True,
        timeout=1800,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    assert "compiling Warp kernels for" in run.stderr
    assert "once per structure (topology)" in run.stderr
    assert "compiling kernels" in run.stderr


@pytest.mark.slow
def test_cli_optimize_says_it_compiles_before_the_search(tmp_path):
    """``tt optimize --method random`` with a fresh kernel cache: Random's warm-up compiles its
    candidates' topologies with the note and the bar on stderr, before the search's clock."""
    _cli_says_it_compiles(
        ["optimize", "--space", "viperx", "--method", "random", "--budget", "2", "--json", str(tmp_path / "r.json")],
        tmp_path,
    )
