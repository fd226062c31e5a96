"""tt.sim: design spaces, target motions, rollouts and the MuJoCo + mink oracle."""
