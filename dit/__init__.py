"""tt.dit."""
