"""heliojax: a JAX-based, purely functional digital twin of a heliostat field.

Conventions (ENU metres, radians inside, PAINT azimuth 0 = south positive east)
are written down once, in :mod:`heliojax._geometry`. Precision-critical code
(geodesy, calibration) needs float64: call
``jax.config.update("jax_enable_x64", True)`` before use (the CLI does; the
library never flips global flags at import).

The package loads lazily (scientific-python SPEC 1, :mod:`lazy_loader`): ``import
heliojax`` is cheap, and each public name, listed with its module in
``__init__.pyi``, is imported on first use (``EAGER_IMPORT=1`` imports everything
at once).
"""

import lazy_loader as _lazy

__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
