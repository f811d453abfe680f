"""One set of numerical kernels on every x86-64 machine, so the same inputs give the same result.

OpenBLAS and NumPy pick their kernels per CPU at load time: on an AVX-512 machine OpenBLAS may
run its SkylakeX kernels and NumPy its X86_V4 loops, on another the Haswell / X86_V3 ones. They
round differently, and a frame solve that has two poses of (nearly) equal objective ends in one
or the other depending on the last bit (measured at stop 39: 2.6 mm against 1.0 mm at one vertex
of the same run). Importing :mod:`retarget_core` therefore pins both to the AVX2 (Haswell,
X86_V3) kernels every such machine runs, through the variables the libraries read when they
load: ``OPENBLAS_CORETYPE`` and ``NPY_DISABLE_CPU_FEATURES``. A value the user set is kept.

This only works before NumPy is loaded. The ``handretarget`` command, the service and their
worker processes import this package first; a script that imports NumPy earlier keeps the
machine's own kernels, and :func:`kernel_provenance` (in every result's provenance) says so.
Machines without AVX2 and FMA, and non-x86 machines, keep their own kernels too."""

from __future__ import annotations

import os
import platform
import sys

#: The OpenBLAS kernel set every x86-64 machine with AVX2 and FMA can run.
OPENBLAS_CORETYPE = "Haswell"
#: NumPy's dispatch targets above AVX2 (numpy 2.x names; an unknown name is ignored with an
#: ImportWarning, which Python does not show by default).
NUMPY_DISABLED = "X86_V4 AVX512_ICL AVX512_SPR"

_STATE: dict = {}


def _cpu_flags() -> set[str]:
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def pin_kernels() -> dict:
    """Set the variables (see the module docstring) unless NumPy is already loaded; returns
    what was done as plain data. Called once, on import of :mod:`retarget_core`."""
    if _STATE:
        return _STATE
    if platform.machine().lower() not in ("x86_64", "amd64"):
        _STATE.update(pinned=False, why=f"not x86-64 ({platform.machine()})")
    elif not {"avx2", "fma"} <= _cpu_flags():
        _STATE.update(pinned=False, why="the CPU has no AVX2 and FMA (or /proc/cpuinfo is unreadable)")
    elif "numpy" in sys.modules:
        _STATE.update(pinned=False, why="numpy was loaded before retarget_core")
    else:
        os.environ.setdefault("OPENBLAS_CORETYPE", OPENBLAS_CORETYPE)
        os.environ.setdefault("NPY_DISABLE_CPU_FEATURES", NUMPY_DISABLED)
        _STATE.update(pinned=True)
    return _STATE


def kernel_provenance() -> dict:
    """What the run's kernels are: pinned or not (and why not), the two variables as the process
    has them, and OpenBLAS's own report of its kernel set per loaded library."""
    info = dict(pin_kernels())
    info["OPENBLAS_CORETYPE"] = os.environ.get("OPENBLAS_CORETYPE", "")
    info["NPY_DISABLE_CPU_FEATURES"] = os.environ.get("NPY_DISABLE_CPU_FEATURES", "")
    try:
        from threadpoolctl import threadpool_info

        info["blas"] = sorted({f"{i.get('internal_api')} {i.get('architecture', '')}".strip()
                               for i in threadpool_info() if i.get("user_api") == "blas"})
    except Exception as exc:  # threadpoolctl is a dependency; a library it cannot read is reported
        info["blas"] = [f"unknown ({type(exc).__name__})"]
    return info
