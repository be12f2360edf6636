"""benchmarks.march_verdicts: the code-path environments and the verdict comparison (the runs
themselves are the benchmark's, minutes per model)."""
from __future__ import annotations

from pathlib import Path

from benchmarks.march_verdicts import _env, same


def test_each_code_path_gets_its_own_flags_and_kernel_cache(tmp_path):
    a, b = _env("avx2", tmp_path), _env("avx512", tmp_path)
    assert (a["TORCHCONN_MARCH"], a["ATEN_CPU_CAPABILITY"]) == ("x86-64-v3", "avx2")
    assert (b["TORCHCONN_MARCH"], b["ATEN_CPU_CAPABILITY"]) == ("x86-64-v4", "avx512")
    assert Path(a["TORCHCONN_CACHE"]) != Path(b["TORCHCONN_CACHE"])
    assert a["OMP_NUM_THREADS"] == b["OMP_NUM_THREADS"] == "1"


def test_verdicts_compare_good_valid_and_hex_count():
    r = {"hex_good": True, "hex_valid": True, "hex_n": 190, "hex_hausdorff": 1e-16}
    assert same({"avx2": r, "avx512": {**r, "hex_hausdorff": 2e-16}})
    assert not same({"avx2": r, "avx512": {**r, "hex_good": False}})
    assert not same({"avx2": r, "avx512": {**r, "hex_n": 191}})
    assert not same({"avx2": r, "avx512": {"error": "timeout 240 s"}})
