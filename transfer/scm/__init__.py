"""Schwarz-Christoffel rectangle maps (a compiled Python replacement for the SC Toolbox's ``rectmap``).

```python
from transfer.scm import RectangleMap, QuadTransfer
f = RectangleMap(vertices, corners=(0, 1, 2, 3))   # counter-clockwise polygon, 4 corner vertex indices
s = f.to_unit_square(w); w = f.from_unit_square(s); f.modulus
t = QuadTransfer(teacher_vertices, learner_vertices); u_L = t(u_T)
```
The first call compiles the kernels (numba, cached on disk afterwards); call :func:`warmup` at start-up to keep
that out of a control loop.
"""

from __future__ import annotations

import numpy as np

from transfer.scm import _ellipj, _evaluate, _parameters, _polygon, _quadrature, _scalar
from transfer.scm._cache import share_source_stamp
from transfer.scm.geometry import as_complex, check_corners, check_polygon, is_simple_ccw, turning_exponents
from transfer.scm.rectmap import QuadTransfer, RectangleMap

#: the kernel modules, by job; their on-disk caches share one key (see ``_cache``): set before anything compiles
_KERNEL_MODULES = (_scalar, _polygon, _quadrature, _parameters, _ellipj, _evaluate)
share_source_stamp(*_KERNEL_MODULES)


def warmup() -> None:
    """Compile (or load from the on-disk cache) every kernel by mapping one point through one transfer."""
    t = QuadTransfer([0, 1, 1 + 1j, 1j], [0, 2, 2 + 1j, 1j])
    t([0.5 + 0.5j, 0.01 + 0.01j])
    RectangleMap([0, 2, 3 + 1j, 1 + 1.5j, -0.5 + 1j], (0, 1, 2, 3)).from_unit_square([0.3 + 0.2j])
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    _polygon.quad_pair_score(square, square)


__all__ = [
    "QuadTransfer",
    "RectangleMap",
    "as_complex",
    "check_corners",
    "check_polygon",
    "is_simple_ccw",
    "turning_exponents",
    "warmup",
]
