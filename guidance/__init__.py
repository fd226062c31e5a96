"""tt.guidance: the model's queries and predicted reward, Zeroth-Order search, Dynamics
Self-Guidance, composition and simulator gradients (the rewards themselves are
`tt.sim.rewards`)."""
