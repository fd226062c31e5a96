"""tt: motion-conditioned robot co-design.

Public API re-exports; the implementation lives in the subpackages
(`tt.sim`, `tt.kernels`, `tt.tokens`, `tt.dit`, `tt.guidance`, `tt.baselines`, `tt.viz`).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("tt")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0.0.0"
