"""tt.sim: design spaces, target motions, rewards, rollouts and the MuJoCo + mink oracle."""
