"""A/B of the warp closed-loop rollout speed of whichever tt is installed: 512 random ViperX
designs on the toss, one thread, CPU seconds.

Run it from outside the repository with each install to compare (benchmarks/results/layering_speed.md).
"""

import inspect
import json
import os
import sys
import time

from tt.sim.designs import get_space
from tt.sim.motions import for_space, get_motion
from tt.sim.rollout import rollout

sp = get_space("viperx")
designs = sp.sample(512, seed=0)
models = [sp.model(d) for d in designs]
ms = for_space([get_motion("toss")], "viperx")
kw = {"threads": 1} if "threads" in inspect.signature(rollout).parameters else {}
rollout(models[:64], ms, backend="warp", device="cpu", **kw)  # compile / cache load
times, cpu = [], []
for _ in range(3):
    t, c = time.perf_counter(), time.process_time()
    ep = rollout(models, ms, backend="warp", device="cpu", **kw)
    times.append(time.perf_counter() - t)
    cpu.append(time.process_time() - c)
steps = ep.qpos.shape[1] * 10 * len(models)  # 10 physics steps per control step
print(
    json.dumps(
        {
            "tree": os.path.dirname(os.path.dirname(sys.modules["tt.kernels"].__file__)),
            "wall_s": times,
            "cpu_s": cpu,
            "world_steps_per_cpu_s": steps / min(cpu),
            "load": os.getloadavg(),
        }
    )
)
