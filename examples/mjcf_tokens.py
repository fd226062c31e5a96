"""Your own MJCF through RoboTokens: tokenize a hand-written arm and rebuild it from its tokens.

    python examples/mjcf_tokens.py [--out DIR]

RoboTokens are the DiT's vocabulary: a token per link (about one per geom or site), two
per joint (one per link it joins), fixed joints between links of one body, and a token per
actuator, each a vector of attributes (geometry, mass, inertia, joint axis and range,
gains). The arm below is written out, tokenized, saved (the .npz that `tt detokenize`
reads), turned back into MJCF, and compared with the original in MuJoCo: same joints and
actuators, same mass, same end-effector pose at random joint angles. About 5 s on a 2-core
CPU. Writes only into --out (default: a new temporary folder). The same on the command line:

    tt tokenize arm.xml --out arm_tokens.npz && tt detokenize arm_tokens.npz --out arm_rebuilt.xml
"""

import argparse
import tempfile
from pathlib import Path

import mujoco
import numpy as np

import tt

ARM = """<mujoco model="arm">
  <compiler angle="radian"/>
  <worldbody>
    <body name="base" pos="0 0 0.05">
      <geom type="cylinder" size="0.05 0.05" density="1000"/>
      <body name="upper" pos="0 0 0.05">
        <joint name="yaw" axis="0 0 1" range="-3 3" damping="0.5"/>
        <joint name="shoulder" axis="0 1 0" range="-1.8 1.8" damping="0.5"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.025" density="800"/>
        <body name="fore" pos="0.3 0 0">
          <joint name="elbow" axis="0 1 0" range="-2.5 2.5" damping="0.3"/>
          <geom type="box" pos="0.12 0 0" size="0.12 0.02 0.02" density="600"/>
          <site name="ee_0" pos="0.25 0 0"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <position joint="yaw" kp="40" forcerange="-8 8"/>
    <position joint="shoulder" kp="60" forcerange="-10 10"/>
    <position joint="elbow" kp="30" forcerange="-5 5"/>
  </actuator>
</mujoco>
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, help="folder for the files (default: a new temporary folder)")
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="tt_tokens_"))
    out.mkdir(parents=True, exist_ok=True)
    (out / "arm.xml").write_text(ARM)

    emb = tt.tokenize(out / "arm.xml")  # also a mujoco.MjModel, a tt Design, or a list of them
    counts = {name: int(n[0]) for name, n in emb.tokens.counts().items() if n[0]}
    print(f"arm.xml: {sum(counts.values())} RoboTokens {counts}")
    emb.tokens.save(out / "arm_tokens.npz")

    rebuilt = tt.detokenize(out / "arm_tokens.npz", model="arm_rebuilt")[0]
    assert rebuilt.ok, rebuilt.error
    (out / "arm_rebuilt.xml").write_text(rebuilt.xml)

    a, b = mujoco.MjModel.from_xml_string(ARM), rebuilt.model
    da, db = mujoco.MjData(a), mujoco.MjData(b)
    site_a, site_b = a.site("ee_0").id, b.site("ee_0").id
    worst = 0.0
    for q in np.random.default_rng(0).uniform(a.jnt_range[:, 0], a.jnt_range[:, 1], size=(100, a.nq)):
        da.qpos[:], db.qpos[:] = q, q  # the round trip keeps the joint order
        mujoco.mj_kinematics(a, da)
        mujoco.mj_kinematics(b, db)
        worst = max(worst, float(np.abs(da.site_xpos[site_a] - db.site_xpos[site_b]).max()))
    print(
        f"joints {a.njnt} -> {b.njnt}, actuators {a.nu} -> {b.nu}, mass {a.body_mass.sum():.4f} -> "
        f"{b.body_mass.sum():.4f} kg, joint ranges within {np.abs(a.jnt_range - b.jnt_range).max():.1e} rad"
    )
    print(f"end-effector position, 100 random joint angles: largest difference {worst:.2e} m")
    print(f"wrote {out / 'arm_rebuilt.xml'} ({len(rebuilt.xml)} characters; the original has {len(ARM)})")


if __name__ == "__main__":
    main()
