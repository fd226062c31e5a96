"""CUDA code generation of every kind of Warp module tt makes, checked on a machine without a GPU.

Warp's NVRTC compiles a module for a CUDA architecture ahead of time with no GPU or driver
(`wp.compile_aot_module(module, arch=..., module_dir=...)`), so a kernel that builds for
the CPU but not for CUDA (device-only intrinsics, a native snippet's CUDA branch, register
or shared-memory limits NVRTC enforces) fails here, in CI, rather than on a user's GPU.

One module per kind, for sm_80 (A100) and sm_90 (H100 / H200) (the differentiable rollout in a
slow test: its compile alone would outlast CI's share; see the test): the fused rollout of one
ViperX topology, its differentiable twin (the simulator gradients), the model controller's
control-step kernel, the start posture and DiffIK step of the MuJoCo-Warp and Newton
backends, the quadruped's whole-body control, and the static modules (mjwarp / newton record
kernels, perturbation noise, the tracking-reward kernel). `test_every_kernel_source_is_covered`
fails when a source file gains Warp kernels that no kind here compiles.

Compiles land in a cache under Warp's kernel cache, keyed by each module's content hash, so a
rerun compiles only what changed; cold, the check takes minutes on 2 cores (the rollout module
dominates; see the measurement in the test's docstring).
"""

from __future__ import annotations

import os
import re
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import warp as wp

ARCHS = (80, 90)
ROOT = Path(__file__).resolve().parents[1]


def _aot_dir() -> Path:
    """Where the CUDA builds are kept between runs (names carry the module's hash)."""
    wp.init()  # sets the kernel cache folder
    return Path(wp.config.kernel_cache_dir) / "tt_cuda_aot"


def _topology_modules() -> dict[str, str]:
    """Kind -> Warp module of the per-topology families, for the nominal ViperX."""
    from tt.kernels.control_step import control_step_kernel
    from tt.kernels.ik import ik_kernel
    from tt.kernels.model import topology_of
    from tt.kernels.rollout import grad_kernels, rollout_kernels, start_posture_kernel
    from tt.sim.designs import get_space

    space = get_space("viperx")
    topo = topology_of(space.model(space.nominal()), space.ee_sites())
    return {
        "rollout": rollout_kernels(topo).module,
        "rollout_grad (simulator gradients)": grad_kernels(topo).module,
        "model controller": control_step_kernel(topo).module.name,
        "start posture (mjwarp, newton)": start_posture_kernel(topo).module.name,
        "DiffIK step (mjwarp, newton)": ik_kernel(topo).module.name,
    }


def _static_modules() -> dict[str, str]:
    """Kind -> Warp module of the kernels defined at import time (and the reward factory)."""
    import tt.kernels.control as control
    import tt.kernels.flat_joints as flat_joints
    import tt.kernels.records as records
    import tt.kernels.rollout as rollout
    import tt.kernels.wbc as wbc
    from tt.kernels.pose import _tracking_reward_kernel

    modules = {
        "whole-body control": wbc._MODULE,
        "perturbation noise": rollout._noise_draws.module.name,
        "tracking reward": _tracking_reward_kernel(1).module.name,
    }
    # The mjwarp backend's controller and record kernels, the newton backend's joint kernels.
    for source in (control, records, flat_joints):
        for name, value in sorted(vars(source).items()):
            if isinstance(value, wp.Kernel):
                modules[f"{source.__name__.rsplit('.', 1)[-1]}.{name}"] = value.module.name
    return modules


def compile_for_cuda(modules: dict[str, str], module_dir: Path, archs=ARCHS, *, overwrites: bool = False) -> list[Path]:
    """Compile every module for every architecture, one job per (module, arch), as many at
    once as there are cores (NVRTC runs outside the GIL). Raises the first failure, naming
    the kind and the architecture. overwrites: build with Warp's
    ``enable_vector_component_overwrites``, as `tt.kernels.rollout.load_differentiable` builds
    the differentiable rollout (Warp reads that flag from its global config at compile time,
    so such modules compile in a batch of their own)."""

    def one(job):
        kind, module, arch = job
        try:
            return wp.compile_aot_module(module, arch=arch, module_dir=module_dir)
        except Exception as err:  # Warp raises several types; say which build failed
            raise RuntimeError(f"CUDA sm_{arch} build of {kind} ({module}) failed: {err}") from err

    jobs = [(kind, module, arch) for kind, module in modules.items() for arch in archs]
    previous = wp.config.enable_vector_component_overwrites
    wp.config.enable_vector_component_overwrites = overwrites
    try:
        with ThreadPoolExecutor(max_workers=max(1, min(len(jobs), os.cpu_count() or 1))) as pool:
            return [path for paths in pool.map(one, jobs) for path in paths]
    finally:
        wp.config.enable_vector_component_overwrites = previous


GRAD_KIND = "rollout_grad (simulator gradients)"


def _check(paths: list[Path], count: int) -> None:
    assert len(paths) == count
    for path in paths:
        assert path.is_file() and path.stat().st_size > 0, path
        assert re.search(r"\.sm(80|90)\.(cubin|ptx)$", path.name), path.name


def test_every_kind_of_tt_module_compiles_for_sm80_and_sm90():
    """Every kind for both architectures but the differentiable rollout: its adjoint makes it
    by far the largest module (its sm_90 build had not finished after 8 CPU minutes, 50
    minutes wall at load ~12, where the forward rollout takes about one), so it has a slow
    test of its own
    (`test_the_differentiable_rollout_compiles_for_sm80_and_sm90`).

    Measured cold (an empty module folder) on the 2-core machine at load average ~2
    (2026-12-01): 98 s wall, 173 CPU seconds for these 16 modules x 2 architectures (at load
    ~12 the same took 14 minutes wall). Warm (cached builds): seconds."""
    modules = {**_topology_modules(), **_static_modules()}
    del modules[GRAD_KIND]
    _check(compile_for_cuda(modules, _aot_dir()), len(ARCHS) * len(modules))


@pytest.mark.slow
def test_the_differentiable_rollout_compiles_for_sm80_and_sm90():
    grad = {GRAD_KIND: _topology_modules()[GRAD_KIND]}
    _check(compile_for_cuda(grad, _aot_dir(), overwrites=True), len(ARCHS))


# A native snippet that is valid C++ for the CPU and broken for CUDA: the CUDA branch calls
# a function that does not exist.
_CUDA_ONLY_BROKEN = """
#if defined(__CUDA_ARCH__)
    return no_such_device_function(x);
#else
    return x;
#endif
"""


@wp.func_native(_CUDA_ONLY_BROKEN)
def _host_only(x: float) -> float: ...


@wp.kernel(module="unique")
def _broken_on_cuda(a: wp.array(dtype=float)):
    i = wp.tid()
    a[i] = _host_only(a[i])


def test_a_cuda_only_codegen_error_fails_the_check(tmp_path):
    a = wp.array([1.5, -2.0], dtype=float, device="cpu")
    wp.launch(_broken_on_cuda, dim=2, inputs=[a], device="cpu")  # the CPU build is fine
    assert a.numpy().tolist() == [1.5, -2.0]
    with pytest.raises(RuntimeError, match=r"CUDA sm_80 build of broken kernel .*failed"):
        compile_for_cuda({"broken kernel": _broken_on_cuda.module.name}, tmp_path, archs=(80,))


def test_every_kernel_source_is_covered():
    """Every source file that defines Warp kernels is one the check above compiles from."""
    covered = {
        "kernels/rollout.py",
        "kernels/wbc.py",
        "kernels/pose.py",
        "kernels/fk.py",
        "kernels/ik.py",
        "kernels/dynamics.py",
        "kernels/control_step.py",
        "kernels/control.py",
        "kernels/records.py",
        "kernels/flat_joints.py",
    }
    # fk and dynamics: their kernels' functions are the rollout's (`kinematics_funcs`,
    # `dynamics_funcs`), which the rollout module compiles.
    found = set()
    for folder in ("tt", "kernels", "sim", "tokens", "dit", "guidance", "baselines", "viz"):
        for path in (ROOT / folder).rglob("*.py"):
            if "@wp.kernel" in path.read_text():
                found.add(path.relative_to(ROOT).as_posix())
    assert found <= covered, f"Warp kernels in {sorted(found - covered)}: add their modules to this test"
