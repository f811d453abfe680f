"""Kernel pinning (retarget_core/kernels.py): importing the package first pins OpenBLAS and
NumPy to the AVX2 kernels on x86-64 machines that have them, keeps a user's own choice, and a
process that loaded NumPy first is reported, not silently left as it is."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from retarget_core.kernels import NUMPY_DISABLED, OPENBLAS_CORETYPE, _cpu_flags

AVX2 = {"avx2", "fma"} <= _cpu_flags()
REPORT = "import json; from retarget_core.kernels import kernel_provenance; print(json.dumps(kernel_provenance()))"


def _report(code: str, **env) -> dict:
    clean = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_CORETYPE", "NPY_DISABLE_CPU_FEATURES")}
    out = subprocess.run([sys.executable, "-c", code], env=clean | env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not AVX2, reason="pinning applies to x86-64 machines with AVX2 and FMA")
def test_importing_the_package_first_pins_both_libraries():
    info = _report("import retarget_core, numpy, scipy.linalg; " + REPORT)
    assert info["pinned"] is True
    assert info["OPENBLAS_CORETYPE"] == OPENBLAS_CORETYPE and info["NPY_DISABLE_CPU_FEATURES"] == NUMPY_DISABLED
    assert info["blas"] and all(b.endswith(OPENBLAS_CORETYPE) for b in info["blas"]), info["blas"]
    # NumPy's own dispatch stops at X86_V3 (AVX2)
    probe = _report("import retarget_core, numpy, json; from numpy._core._multiarray_umath import __cpu_features__ as f; "
                    "print(json.dumps({k: bool(f.get(k)) for k in ('X86_V3', 'X86_V4')}))")
    assert probe == {"X86_V3": True, "X86_V4": False}


@pytest.mark.skipif(not AVX2, reason="pinning applies to x86-64 machines with AVX2 and FMA")
def test_a_users_own_kernel_choice_is_kept():
    info = _report("import retarget_core; " + REPORT, OPENBLAS_CORETYPE="Sandybridge")
    assert info["OPENBLAS_CORETYPE"] == "Sandybridge"
    assert all(b.endswith("Sandybridge") for b in info["blas"]), info["blas"]


def test_numpy_loaded_first_is_reported():
    info = _report("import numpy; import retarget_core; " + REPORT)
    assert info["pinned"] is False
    assert "numpy was loaded before" in info["why"] or not AVX2
