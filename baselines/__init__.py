"""tt.baselines."""
