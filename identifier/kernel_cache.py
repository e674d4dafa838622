"""Whether this machine has compiled the identifier's kernels (``identifier/kernels.py``), without
importing numba to find out.

numba caches each compiled kernel beside its source (``cache=True``), so only the first use on a machine
pays the compilation; every later process loads the cache.  The first use should not happen unseen inside
a TCU child process, where the plant waits for the TCU with a start-up timeout and the user sees nothing:
``hil run`` and ``hil tcu`` ask ``fresh()`` first and, when it says no, compile in the foreground with a
progress bar (``compile_all``).

The stamp ``__pycache__/kernels-compiled.json`` beside the source records what the cache was built from:
the source's SHA-256, numba's version, the Python version and the target numba compiles for (the host
CPU as numba's cache keys it).  ``compile_all`` writes it
after ``kernels.warm_up`` has compiled (or loaded) every kernel.  A stamp that differs, or none, means
"not compiled here"; where the directory is not writable there is no stamp and ``fresh()`` always says no
(the caller then warms the kernels up in the foreground each time: loading them from numba's user cache).
"""
from __future__ import annotations

import hashlib
import json
import platform
import sys
from importlib import metadata
from pathlib import Path

SOURCE = Path(__file__).with_name("kernels.py")
STAMP = SOURCE.parent / "__pycache__" / "kernels-compiled.json"


def _host() -> dict:
    """The target numba compiles for, as numba's cache keys it (``codegen.magic_tuple``: the triple, the host
    CPU's name and features), read from llvmlite, which imports quickly where numba does not.
    Read by CPUID, so a guest kernel (User-Mode Linux) on the same CPU is the same host."""
    try:
        from llvmlite import binding
    except ImportError:  # no llvmlite: keyed by the machine alone
        return {"machine": platform.machine()}
    return {"triple": binding.get_process_triple(), "cpu": binding.get_host_cpu_name(),
            "features": binding.get_host_cpu_features().flatten()}


def _identity() -> dict:
    """What the compiled cache depends on."""
    try:
        numba_version = metadata.version("numba")
    except metadata.PackageNotFoundError:  # numba absent: the stamp says so
        numba_version = None
    return {"source_sha256": hashlib.sha256(SOURCE.read_bytes()).hexdigest(), "numba": numba_version,
            "python": sys.version.split()[0], **_host()}


def fresh() -> bool:
    """True when this machine's cache holds every kernel of this source (the stamp matches)."""
    try:
        return json.loads(STAMP.read_text()) == _identity()
    except (OSError, ValueError):  # no stamp or a damaged one: not fresh, compiled again
        return False


def mark() -> None:
    """Record that every kernel was just compiled (or loaded) here; silent where it cannot write."""
    try:
        STAMP.parent.mkdir(exist_ok=True)
        tmp = STAMP.with_suffix(".tmp")
        tmp.write_text(json.dumps(_identity()))
        tmp.replace(STAMP)
    except OSError:  # a read-only tree: the next run compiles again
        pass


def compile_all(progress=None) -> bool:
    """Compile every kernel now unless ``fresh()``; ``progress(done, total, name)`` as in
    ``kernels.warm_up``.  True when it compiled (or loaded) them, False when they were fresh already or
    numba is not available (the strategies then run their numpy references)."""
    if fresh():
        return False
    from . import kernels

    if not kernels.AVAILABLE:
        return False
    kernels.warm_up(progress)
    mark()                      # every kernel is in numba's cache now: later runs need not show a compile
    return True
