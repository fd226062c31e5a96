"""tt.sim: design spaces, target motions, rewards, rollouts and the MuJoCo + mink oracle.

`designs/` (grammars -> MJCF), `motions/` (the skill library, files), `rewards.py`,
`controller.py` / `wbc.py` (the oracle's controllers), `validate.py` (the oracle),
`rollout.py` (``rollout()`` and the warp backend), `backends/` (the backend interface, its
registry and the one design -> model resolver), `mjwarp_backend.py`, `newton_backend.py`.
"""
