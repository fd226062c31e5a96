"""tt.viz."""
