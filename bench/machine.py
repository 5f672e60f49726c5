"""The machine and resources a record was made with: platform, CPU model, the settings that
change speed but no number, and the CPUs and accelerators a run may use."""
from __future__ import annotations

import os
import platform
import subprocess

import jax

_REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def git_revision() -> str | None:
    try:
        out = subprocess.run(["git", "-C", _REPO, "rev-parse", "HEAD"], capture_output=True,
                             text=True, timeout=5)
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def cpu_model(cpuinfo: str | None = None) -> str | None:
    """The CPU's model as Linux names it, "<model name> (family F, model M)", from
    /proc/cpuinfo (`cpuinfo`: its text, for tests); None where there is none to read
    (`platform.processor()` is empty on Linux). Speed ratios depend on it, so speed records
    name it."""
    if cpuinfo is None:
        try:
            with open("/proc/cpuinfo") as f:
                cpuinfo = f.read()
        except OSError:
            cpuinfo = ""
    first = cpuinfo.split("\n\n", 1)[0]  # the first processor's block
    fields = {key.strip(): value.strip() for key, sep, value in
              (line.partition(":") for line in first.splitlines()) if sep}
    name = fields.get("model name")
    if not name:
        return platform.processor() or None
    if "cpu family" in fields and "model" in fields:
        return f"{name} (family {fields['cpu family']}, model {fields['model']})"
    return name


def speed_settings() -> dict:
    """What changes speed but no number, as records and the speed CSVs name it: `xla_flags`
    (the environment's XLA_FLAGS, None unset), `malloc_hugetlb` (glibc's huge-page tunable,
    `bench.malloc`; None unset) and `cpu_model`."""
    from bench.malloc import hugetlb
    return {"xla_flags": os.environ.get("XLA_FLAGS") or None,
            "malloc_hugetlb": hugetlb(os.environ), "cpu_model": cpu_model()}


def machine() -> dict:
    """The machine a record was made on, with its `speed_settings`: a run's updates per
    budget depend on them."""
    return {"platform": platform.platform(), "processor": platform.processor(),
            "cpus": os.cpu_count(), "python": platform.python_version(),
            "jax_devices": [str(d) for d in jax.devices()], **speed_settings()}


def resources() -> dict:
    """What this run may use: CPUs in its affinity set (taskset / cgroup pinning; under Ray,
    the CPUs the cell reserved) and accelerators JAX sees. Recorded in every record: runs
    compare only at equal resources."""
    if os.environ.get("ILDBENCH_CPUS_PER_RUN"):  # set by an executor that reserves CPUs (Ray)
        cpus = int(float(os.environ["ILDBENCH_CPUS_PER_RUN"]))
    else:
        try:
            cpus = len(os.sched_getaffinity(0))
        except AttributeError:  # not on Linux
            cpus = os.cpu_count() or 1
    gpus = sum(d.platform != "cpu" for d in jax.devices())
    return {"cpus": cpus, "gpus": gpus}
