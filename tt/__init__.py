"""tt: motion-conditioned robot co-design.

The implementation lives in the subpackages, layered high -> low: the app (`tt.cli`,
`tt.demo`, `tt.report`, `tt.generate`, `tt.optimizers`) > `tt.viz` > `tt.guidance` >
`tt.baselines` > `tt.dit` > `tt.tokens` > `tt.sim` > `tt.kernels`; imports only go down.
"""

from tt.kernels.errors import TTError
from tt.kernels.version import tt_version

__version__ = tt_version()

__all__ = ["TTError", "__version__"]
