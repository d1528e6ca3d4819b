"""The machine a benchmark ran on, named beside its figures: CPU model, vector extensions, cores, load.

Why every benchmark says it: the machines are shared and a session may land on another CPU (AVX-512 one
day, AVX2 the next); a figure without its CPU cannot be compared with the next run's. Read from Linux's
/proc/cpuinfo (no `lscpu` needed); elsewhere `platform.processor()` names the model and the extensions are
unknown. Imported by the scripts beside it (`from machine import cpu_name`: a script's own folder is on
its import path).
"""

from __future__ import annotations

import os
import platform
from pathlib import Path

from branchrange.commands.train_segmenter import usable_cores

CPUINFO = Path("/proc/cpuinfo")


def cpu_description(cpuinfo: Path = CPUINFO) -> dict:
    """{"model": str, "cores": cores this process may run on, "avx2": bool | None, "avx512": bool | None,
    "load_average_1min": float | None} — None where the system does not say (no `cpuinfo` file, no load
    average). `cpuinfo`: a /proc/cpuinfo-format file (its first "model name" and "flags" lines count)."""
    model, flags = "", None
    try:
        for line in cpuinfo.read_text(encoding="utf-8", errors="replace").splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and not model:
                model = value.strip()
            elif key.strip() == "flags" and flags is None:
                flags = set(value.split())
    except OSError:
        pass
    try:
        load: float | None = round(os.getloadavg()[0], 2)
    except (AttributeError, OSError):
        load = None
    return {
        "model": model or platform.processor() or "unknown CPU",
        "cores": usable_cores(),
        "avx2": None if flags is None else "avx2" in flags,
        "avx512": None if flags is None else "avx512f" in flags,
        "load_average_1min": load,
    }


def cpu_name(cpuinfo: Path = CPUINFO) -> str:
    """One line for a table's heading or a JSON's "cpu", e.g. 'AMD EPYC 9B14; AVX2 yes, AVX-512 yes; 2 cores'."""
    cpu = cpu_description(cpuinfo)

    def said(present: bool | None) -> str:
        return "unknown" if present is None else "yes" if present else "no"

    return f"{cpu['model']}; AVX2 {said(cpu['avx2'])}, AVX-512 {said(cpu['avx512'])}; {cpu['cores']} cores"


def process_stat_fields(pid: int) -> list[str] | None:
    """The fields of Linux's /proc/PID/stat after the process's name (its third field, the state, first: field
    k of `man 5 proc` is item k − 3), None when the process is gone or there is no /proc. The name is cut at its
    last ")": it may hold spaces and brackets itself."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
