"""One on-disk cache key for all the SC map's kernel modules, so that editing one kernel file recompiles every kernel.

numba keys a function's cache on its own source file only (the SHA-256 of the file; numba's docs, "Cache
invalidation", and numba's issue tracker,
https://github.com/numba/numba/issues/1833): a kernel compiled with a callee from another file is loaded from the cache
unchanged after that callee's file changes, and would run the old callee. One kernel file had none of that risk; split
by job (``_polygon``, ``_quadrature``, ``_parameters``, ``_ellipj``, ``_evaluate``) it would. :func:`share_source_stamp`
gives all their caches one source stamp, the hash of all their files' stamps (which numba has already computed,
nothing is read here): a change to any kernel file invalidates every kernel's cache, as it did with one file.
"""

from __future__ import annotations

import hashlib
from types import ModuleType

from numba.core.caching import NullCache
from numba.core.registry import CPUDispatcher


def kernel_dispatchers(*modules: ModuleType) -> list[CPUDispatcher]:
    """The compiled functions defined in ``modules`` (each once, in the module that defines it)."""
    return [v for m in modules for v in vars(m).values()
            if isinstance(v, CPUDispatcher) and v.py_func.__module__ == m.__name__]


def share_source_stamp(*modules: ModuleType) -> bytes:
    """Key the on-disk caches of every kernel in ``modules`` on all their source files together; the shared stamp.

    Must run before any of them compiles (``transfer.scm.__init__`` runs it at import; nothing compiles at import).
    Relies on numba's ``Cache._cache_file._source_stamp`` (numba is pinned in requirements.lock;
    tests/unit/transfer/scm/test_rectmap.py checks that an edit to a callee's file recompiles its caller in another
    file)."""
    files = [d._cache._cache_file for d in kernel_dispatchers(*modules) if not isinstance(d._cache, NullCache)]
    shared = hashlib.sha256("\n".join(sorted({repr(f._source_stamp) for f in files})).encode()).digest()
    for f in files:
        f._source_stamp = shared
    return shared
