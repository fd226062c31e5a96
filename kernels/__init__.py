"""tt.kernels."""
