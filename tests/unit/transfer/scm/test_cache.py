"""transfer/scm/_cache.py: one on-disk cache key for all the SC map's kernel modules.

That transfer.scm shares one key over its kernel modules and that an edit to a callee's file recompiles its caller
(in fresh processes) is tested in tests/unit/transfer/scm/test_rectmap.py; here :func:`kernel_dispatchers` and
:func:`share_source_stamp` on two small modules of the test's own (never on transfer.scm's, whose stamps the
import has already shared)."""

from __future__ import annotations

import hashlib
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

from transfer.scm._cache import kernel_dispatchers, share_source_stamp

CALLEE = "from numba import njit\n\n@njit(cache=True)\ndef g(x):\n    return x + 1\n\n@njit\ndef h(x):\n    return x\n"
CALLER = ("from numba import njit\nfrom {callee} import g\n\n@njit(cache=True)\ndef f(x):\n    return g(x) * 2\n\n"
          "def plain(x):\n    return x\n")


def _load(path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(path.stem, path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = mod
    spec.loader.exec_module(mod)
    return mod


def test_kernel_dispatchers_lists_each_compiled_function_once_where_it_is_defined(tmp_path: Path) -> None:
    callee_name, caller_name = f"cache_callee_{tmp_path.name}", f"cache_caller_{tmp_path.name}"
    (tmp_path / f"{callee_name}.py").write_text(CALLEE)
    (tmp_path / f"{caller_name}.py").write_text(CALLER.format(callee=callee_name))
    sys.path.insert(0, str(tmp_path))
    try:
        callee, caller = _load(tmp_path / f"{callee_name}.py"), _load(tmp_path / f"{caller_name}.py")
        names = sorted(d.py_func.__name__ for d in kernel_dispatchers(callee, caller))
        assert names == ["f", "g", "h"]  # g once (not again as the caller's import), no plain function
        assert [d.py_func.__name__ for d in kernel_dispatchers(caller)] == ["f"]

        stamp = share_source_stamp(callee, caller)
        cached = [d for d in kernel_dispatchers(callee, caller) if d.py_func.__name__ != "h"]  # h has no disk cache
        assert {d._cache._cache_file._source_stamp for d in cached} == {stamp}
        assert isinstance(stamp, bytes) and len(stamp) == hashlib.sha256().digest_size
        assert caller.f(1) == 4  # the kernels still compile and run with the shared key
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop(callee_name, None)
        sys.modules.pop(caller_name, None)


def test_no_modules_share_the_stamp_of_nothing() -> None:
    assert kernel_dispatchers() == []
    assert share_source_stamp() == hashlib.sha256(b"").digest()
