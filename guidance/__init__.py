"""tt.guidance: rewards, Zeroth-Order search and Dynamics Self-Guidance."""
