"""Generated, compiled code for CasADi functions (the MPC's real-time iteration), built once per machine and cached.

:func:`compile_functions` writes the C code CasADi generates for a set of functions, builds it with the system's C
compiler into a shared library named by the hash of that code (and of the compiler and CasADi versions), and loads
the functions back from it. The library lives in the cache directory (:func:`bridge.core.paths.cache_dir`,
``mpc/``); a later start, or another process, finds it there and loads it in milliseconds. Building happens when a
node builds its teacher, never in a control loop; two processes building the same library at once each write their
own file and the last rename wins (the files are identical).

A machine without a working C compiler (none on the path, a failed build, a cache it cannot write) keeps the
functions as they are, interpreted by CasADi's virtual machine, and says so once in one line: slower, same results.
``SCMBRIDGE_NO_COMPILE=1`` asks for the interpreted functions on purpose (the test suite's stations, which start
and stop by the hundred, use it; the compiled path has its own tests).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import logging
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

from bridge.core.paths import cache_dir

log = logging.getLogger("scmbridge.codegen")

#: compiler flags: -O2 makes the generated code several times faster than -O0 and builds in seconds
CFLAGS = ("-O2", "-fPIC", "-shared")
#: the longest a build may take, s (a cold build of the MPC's functions takes seconds to tens of seconds)
BUILD_TIMEOUT = 300.0

_loaded: dict[str, list] = {}  # library path -> its functions: every MPC of a process shares one library
_warned: set[str] = set()


def _warn_once(text: str) -> None:
    if text not in _warned:
        _warned.add(text)
        log.warning("%s", text)  # without a configured handler, logging's last resort prints it on stderr


def c_compiler() -> str | None:
    """The C compiler to use: ``$CC`` if set, else ``cc`` (or ``gcc``) on the path; None if there is none."""
    for name in (os.environ.get("CC"), "cc", "gcc"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


@functools.lru_cache(maxsize=4)
def _compiler_id(cc: str) -> str:
    """The compiler's version line (part of the library's name): asked once per process, not per MPC built."""
    try:
        out = subprocess.run([cc, "--version"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return cc
    return out.splitlines()[0] if out else cc


def compile_functions(functions: Sequence, cache: Path | None = None) -> list | None:
    """The ``functions`` (CasADi ``Function`` objects) loaded from a compiled library built from their generated
    code, or None (with a one-line warning) where that cannot be done; see the module docstring."""
    import casadi as ca

    if os.environ.get("SCMBRIDGE_NO_COMPILE", "") not in ("", "0"):
        return None
    cc = c_compiler()
    if cc is None:
        _warn_once("no C compiler (cc, gcc or $CC): the MPC runs interpreted (slower, same results)")
        return None
    gen = ca.CodeGenerator("scmbridge_kernels.c", {"with_header": False})
    for fn in functions:
        gen.add(fn)
    source = gen.dump()
    digest = hashlib.sha256("\0".join([source, ca.__version__, _compiler_id(cc), " ".join(CFLAGS)]).encode())
    where = (cache or cache_dir()) / "mpc"
    lib = where / f"kernels-{digest.hexdigest()[:20]}.so"
    if str(lib) in _loaded:
        return _loaded[str(lib)]
    try:
        if not lib.exists():
            _build(cc, source, lib)
        loaded = [ca.external(fn.name(), str(lib)) for fn in functions]
    except (OSError, RuntimeError, subprocess.SubprocessError) as exc:
        _warn_once(f"could not build the MPC's compiled code ({str(exc).splitlines()[0][:200]}): it runs "
                   "interpreted (slower, same results)")
        return None
    _loaded[str(lib)] = loaded
    return loaded


def _build(cc: str, source: str, lib: Path) -> None:
    """Compile ``source`` into ``lib`` through a private temporary file, renamed into place when complete."""
    lib.parent.mkdir(parents=True, exist_ok=True)
    log.info("building the MPC's compiled code into %s (once per machine)", lib)
    with tempfile.TemporaryDirectory(dir=lib.parent) as tmp:
        src = Path(tmp) / "kernels.c"
        src.write_text(source)
        out = Path(tmp) / lib.name
        done = subprocess.run([cc, *CFLAGS, str(src), "-o", str(out), "-lm"], capture_output=True, text=True,
                              timeout=BUILD_TIMEOUT)
        if done.returncode != 0:
            raise RuntimeError(f"{Path(cc).name} failed: {(done.stderr or done.stdout).strip()[:300]}")
        os.replace(out, lib)


@contextlib.contextmanager
def native_stdout_to_stderr() -> Iterator[None]:
    """Send what native code writes on file descriptor 1 to descriptor 2 meanwhile, without qpOASES's licence
    banner. qpOASES prints it from its solver's constructor (``QProblemB``: "if options.printLevel != PL_NONE", on the
    default options, before CasADi's plugin sets ``printLevel`` to ``none``), on stdout, each time a solver's memory
    is made (twice per robot: the solver and its buffer): it would corrupt a command's JSON output (``bench``) and is
    no news in a service's log. No option reaches that constructor, so the banner is taken out here (said once at
    debug level); everything else native code wrote is passed on as it is."""
    sys.stdout.flush()
    saved = os.dup(1)
    with tempfile.TemporaryFile() as caught:
        try:
            os.dup2(caught.fileno(), 1)
            yield
        finally:
            os.dup2(saved, 1)
            os.close(saved)
            caught.seek(0)
            text = _without_repeated_banners(caught.read().decode("utf-8", "replace"))
            if text.strip():
                sys.stderr.write(text)
                sys.stderr.flush()


#: the first and the last line of qpOASES's licence banner
_BANNER = ("qpOASES -- An Implementation of the Online Active Set Strategy.",
           "See the GNU Lesser General Public License for more details.")
_banner_said = False


def _without_repeated_banners(text: str) -> str:
    """``text`` without qpOASES's licence banners (the first one of the process said at debug level)."""
    global _banner_said
    out: list[str] = []
    skipping = False
    for line in text.splitlines(keepends=True):
        if line.strip() == _BANNER[0]:
            skipping = True
            if not _banner_said:
                _banner_said = True
                logging.getLogger("scmbridge.mpc").debug("qpOASES's licence banner left out of the log")
        if not skipping:
            out.append(line)
        if line.strip() == _BANNER[1]:
            skipping = False
    return "".join(out)


def build_mpc(config, compile: bool = False):
    """An :class:`~transfer.teacher.mpc.MpcTeacher` for ``config`` made the way every node makes one: the solvers'
    banners kept off stdout and, with ``compile``, the real-time iteration's functions compiled now (cached; a
    station builds them in the background instead)."""
    from transfer.teacher.mpc import MpcTeacher

    with native_stdout_to_stderr():
        return MpcTeacher(config, compiler=compile_functions if compile and config.solver != "ipopt" else None)
