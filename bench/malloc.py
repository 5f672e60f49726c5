"""Huge pages for XLA's per-call working memory (glibc's `glibc.malloc.hugetlb` tunable).

XLA's CPU runtime mallocs each call's working memory (for an ILD update, the residuals its
backward pass reads: 191 MiB on hopper at B = 32) and frees it when the call ends. glibc
serves an allocation that large with a fresh anonymous mapping and unmaps it on free, so
every call pays one page fault per 4 KiB page it touches (tens of thousands per hopper
update, a fifth of its time in the kernel). With the tunable
`glibc.malloc.hugetlb=1` (glibc >= 2.35) malloc advises the kernel to back its mappings with
2 MiB transparent huge pages, which cuts the faults 30-100-fold (pointmass, hopper) where
the kernel's transparent huge pages are `madvise` or `always`. It changes where
memory comes from, not what is computed: the same numbers bit for bit (tested).

glibc reads tunables when a process starts, so the `ildbench` command (and the speed
benchmarks) re-execute themselves once with the tunable added to GLIBC_TUNABLES. Set
ILDBENCH_HUGEPAGES=0 to run without it; records name the setting (`machine.malloc_hugetlb`).
"""
from __future__ import annotations

import os
import platform
import re
import sys
from typing import Mapping

TUNABLE = "glibc.malloc.hugetlb"
OFF = "ILDBENCH_HUGEPAGES"
THP_PATH = "/sys/kernel/mm/transparent_hugepage/enabled"
_DONE = "ILDBENCH_HUGEPAGES_SET"


def thp_mode(path: str = THP_PATH) -> str | None:
    """The kernel's transparent-huge-page mode ('always', 'madvise', 'never'); None where
    the kernel does not say (not Linux)."""
    try:
        with open(path) as f:
            m = re.search(r"\[(\w+)\]", f.read())
    except OSError:
        return None
    return m.group(1) if m else None


def glibc_version() -> tuple[int, int] | None:
    """(major, minor) of the C library Python runs on, if it is glibc."""
    name, version = platform.libc_ver()
    if name != "glibc" or not re.match(r"\d+\.\d+", version or ""):
        return None
    major, minor = version.split(".")[:2]
    return int(major), int(re.match(r"\d+", minor).group())


def hugetlb(env: Mapping[str, str] = os.environ) -> str | None:
    """The value `env`'s GLIBC_TUNABLES gives `glibc.malloc.hugetlb` (None: not set)."""
    for item in env.get("GLIBC_TUNABLES", "").split(":"):
        name, _, value = item.partition("=")
        if name == TUNABLE:
            return value
    return None


def env_with_hugepages(env: Mapping[str, str]) -> dict | None:
    """`env` with `glibc.malloc.hugetlb=1` added to its GLIBC_TUNABLES; None where there is
    nothing to add: the tunable is set already (either way), ILDBENCH_HUGEPAGES=0 turns it
    off, the process was re-executed for it already (ILDBENCH_HUGEPAGES_SET), or it cannot
    act here (not glibc >= 2.35, or transparent huge pages 'never' or
    absent)."""
    if env.get(OFF) == "0" or hugetlb(env) is not None or env.get(_DONE):
        return None
    if (glibc_version() or (0, 0)) < (2, 35) or thp_mode() in (None, "never"):
        return None
    given = env.get("GLIBC_TUNABLES")
    return {**env, "GLIBC_TUNABLES": f"{given}:{TUNABLE}=1" if given else f"{TUNABLE}=1",
            _DONE: "1"}  # never twice, even where the C library dropped the tunable


def reexec_with_hugepages(module: str | None = None) -> None:
    """Re-execute this process as `python -m <module> <the same arguments>` (without a
    module, as `python <the same script and arguments>`: a script run by path) with the
    tunable (`env_with_hugepages`); returns where there is nothing to add. For command-line
    entry points only: it replaces the running process."""
    env = env_with_hugepages(os.environ)
    if env is None:
        return
    sys.stdout.flush()
    sys.stderr.flush()
    argv = ["-m", module, *sys.argv[1:]] if module else sys.argv
    os.execve(sys.executable, [sys.executable, *argv], env)
