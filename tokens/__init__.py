"""tt.tokens."""
