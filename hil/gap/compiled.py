"""A CasADi function compiled to C once per machine, with CasADi's virtual machine as the fallback.

The gap diagnosis spends nearly all its time simulating whole runs: the period step of
``hil.gap.model.Simulator`` (ten RK4 sub-steps) rolled over every period, hundreds of times per
least-squares fit.  CasADi's virtual machine interprets each instruction; the same instructions as C,
compiled without fast-math and without FMA contraction, give the same IEEE operations in the same
order, so the same bits, faster (docs/design/gap-diagnosis.md measures it).

``compiled(fn)`` generates ``fn``'s C (``casadi.CodeGenerator``) and compiles it into a shared library
named by the SHA-256 of that source, the compiler's version and its flags.  The library is kept in
``__pycache__/casadi-c`` beside this file (as numba keeps the identifier's kernels), or in a directory
of this process's own when that one cannot be written; a later call with the same function loads it
without compiling.  Two processes compiling the same source each write a file of their own and rename
it into place, so neither reads a half-written library.  The cache keeps the ``KEEP`` libraries used
last (a forward selection's steps carry the first effect's fitted values: a new source each time);
older ones are removed when a new one is written.  With no C compiler (``$CC``, else ``cc``, ``gcc``),
or when compiling fails, ``fn`` itself is returned: slower, the same numbers.
"""
from __future__ import annotations

import functools
import hashlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import casadi as ca

#: no -ffast-math and no -march: the compiler must not reorder, contract (FMA) or approximate, so the
#: compiled function computes what the virtual machine computes, bit for bit
FLAGS = ("-O1", "-fPIC", "-shared", "-ffp-contract=off")
CACHE = Path(__file__).resolve().parent / "__pycache__" / "casadi-c"
KEEP = 300
_own_cache: list[Path] = []


@functools.lru_cache(maxsize=None)
def _compiler() -> tuple[str, str] | None:
    """(the C compiler's path, the first line of its ``--version``), or None."""
    for name in (os.environ.get("CC", ""), "cc", "gcc"):
        path = shutil.which(name) if name else None
        if path:
            try:
                out = subprocess.run([path, "--version"], capture_output=True, text=True, timeout=30).stdout
            except (OSError, subprocess.SubprocessError):   # this name is no working compiler: try the next
                continue
            return path, (out.splitlines() or [""])[0]
    return None


def _cache_dir() -> Path:
    try:
        CACHE.mkdir(parents=True, exist_ok=True)
        if os.access(CACHE, os.W_OK):
            return CACHE
    except OSError:                   # the shared cache cannot be made here: a private one below
        pass
    if not _own_cache:
        _own_cache.append(Path(tempfile.mkdtemp(prefix="hil-casadi-c-")))
    return _own_cache[0]


def _touch(lib: Path) -> None:
    try:
        os.utime(lib)
    except OSError:                   # a read-only cache: the library is used all the same, only pruned sooner
        pass


def _prune(cache: Path) -> None:
    """Remove all but the ``KEEP`` libraries used last (a process that loaded one keeps its mapping)."""
    try:
        libs = sorted(cache.glob("*.so"), key=lambda p: p.stat().st_mtime, reverse=True)
        for old in libs[KEEP:]:
            old.unlink(missing_ok=True)
    except OSError:                   # another process pruned or holds it: pruning is housekeeping only
        pass


def compiled(fn: ca.Function) -> ca.Function:
    """``fn`` as a compiled library (loaded from the cache, or compiled into it), else ``fn`` itself."""
    found = _compiler()
    if found is None:
        return fn
    cc, version = found
    with tempfile.TemporaryDirectory(prefix="hil-casadi-src-") as tmp:
        gen = ca.CodeGenerator("step.c", {"with_header": False})
        gen.add(fn)
        gen.generate(tmp + os.sep)
        source = (Path(tmp) / "step.c").read_bytes()
        key = hashlib.sha256(source + "\0".join((version, *FLAGS, ca.__version__)).encode())
        cache = _cache_dir()
        lib = cache / f"{fn.name()}-{key.hexdigest()[:24]}.so"
        if not lib.exists():
            part = cache / f"{lib.name}.{os.getpid()}.part"
            try:
                subprocess.run([cc, *FLAGS, str(Path(tmp) / "step.c"), "-o", str(part), "-lm"],
                               check=True, capture_output=True, timeout=120)
                os.replace(part, lib)
            except (OSError, subprocess.SubprocessError):   # the compiler failed: the virtual machine's same bits
                part.unlink(missing_ok=True)
                return fn
            _prune(cache)
        else:
            _touch(lib)
    try:
        return ca.external(fn.name(), str(lib))
    except RuntimeError:              # CasADi cannot load the library: the virtual machine's same bits
        return fn
