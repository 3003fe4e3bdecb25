"""Constants and the one scalar helper every compiled kernel of the SC rectangle map shares (numba, cached on disk).

The kernels are split by job: ``_polygon`` (polygon checks), ``_quadrature`` (Gauss-Jacobi tables and the strip
map's integrals), ``_parameters`` (the quadrilateral's parameter solve), ``_ellipj`` (complex sn, cn, dn) and
``_evaluate`` (rectangle <-> strip <-> polygon, forward, inverse and the fused transfer). The maths follows the
SC Toolbox (Driscoll; docs/ARCHITECTURE.md section 9); ``transfer.scm.__init__`` keys their on-disk caches on all
their files together (``_cache.share_source_stamp``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

PI = math.pi
LOG2 = math.log(2.0)
EPS = 2.220446049250313e-16


@njit(cache=True, error_model="numpy")
def _sdiv(a: complex, b: complex) -> complex:
    """a / b, NaN (not an exception: numba raises on complex division by zero) when b == 0."""
    if b == 0.0:
        return complex(np.nan, np.nan)
    return a / b

