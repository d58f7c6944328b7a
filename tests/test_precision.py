"""Compute precision: chosen from the hardware, honoured when asked for, recorded in the map."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
import torch

import slamreloc.runtime.precision as precision_module
from slamreloc.localize.localizer import make_localizer
from slamreloc.runtime.precision import EmulatedBf16Warning, bf16_support, resolve_precision

PROBE = ("import json; from slamreloc.runtime.precision import bf16_support, resolve_precision; "
         "print(json.dumps([resolve_precision('auto'), bf16_support('cpu')[1]]))")


def _probe(**env) -> tuple[str, str]:
    res = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True,
                         env={**os.environ, **env}, check=True)
    return tuple(json.loads(res.stdout))


def test_auto_follows_native_support():
    native, reason = bf16_support("cpu")
    assert resolve_precision("auto", "cpu") == ("bf16" if native else "fp32")
    assert reason


def test_restricting_onednn_and_aten_to_avx2_means_fp32():
    """The AVX2 imitation on a bf16-capable CPU must take the fp32 path, like a real AVX2 CPU."""
    precision, reason = _probe(ONEDNN_MAX_CPU_ISA="AVX2", ATEN_CPU_CAPABILITY="avx2")
    assert precision == "fp32"
    assert "CPU" in reason


# (CPU flags, ONEDNN_MAX_CPU_ISA, ATen capability) -> what auto picks for training / queries
HARDWARE = [
    ({"avx512_bf16", "amx_bf16", "amx_tile"}, "", "AVX512", "bf16", "bf16"),
    ({"avx512_bf16", "amx_bf16"}, "AVX512_CORE_AMX", "AVX512", "bf16", "bf16"),
    ({"avx512_bf16", "amx_bf16"}, "AVX512_CORE_BF16", "AVX512", "bf16", "fp32"),
    ({"avx512_bf16"}, "", "AVX512", "bf16", "fp32"),
    ({"avx512_bf16", "amx_bf16"}, "AVX2", "AVX512", "fp32", "fp32"),
    ({"avx512_bf16", "amx_bf16"}, "", "AVX2", "fp32", "fp32"),
    ({"avx2", "fma"}, "", "AVX2", "fp32", "fp32"),
]


@pytest.mark.parametrize("flags, cap, aten, train, query", HARDWARE)
def test_auto_for_training_and_for_queries(monkeypatch, flags, cap, aten, train, query):
    """bf16 trains faster wherever it is native; a query's single small batch only gains from
    it with AMX (BENCHMARKS.md, "Query precision by hardware")."""
    monkeypatch.setattr(precision_module, "_cpu_flags", lambda: set(flags))
    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda: aten)
    monkeypatch.delenv("DNNL_MAX_CPU_ISA", raising=False)
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", cap)
    precision_module.bf16_kind.cache_clear()
    try:
        assert resolve_precision("auto", "cpu") == train
        assert resolve_precision("auto", "cpu", use="query") == query
        assert bf16_support("cpu")[0] == (train == "bf16")
    finally:
        precision_module.bf16_kind.cache_clear()


def test_the_localizer_asks_for_query_precision(small_map):
    localizer = make_localizer(small_map, "regressor", guided=None)
    assert localizer.precision == resolve_precision("auto", "cpu", use="query")
    with pytest.raises(ValueError, match="unknown use"):
        resolve_precision("auto", "cpu", use="serve")


def test_explicit_requests_are_honoured():
    assert resolve_precision("fp32", "cpu") == "fp32"
    native, _ = bf16_support("cpu")
    if native:
        assert resolve_precision("bf16", "cpu") == "bf16"
    else:
        with pytest.warns(EmulatedBf16Warning, match="slower"):
            assert resolve_precision("bf16", "cpu") == "bf16"


def test_unknown_precision_is_refused():
    with pytest.raises(ValueError, match="unknown precision"):
        resolve_precision("fp8", "cpu")


def test_map_records_its_training_precision(small_map):
    assert small_map.meta["train"]["precision"] == resolve_precision("auto", "cpu")


def test_cli_rejects_unknown_precision(scene_dir, tmp_path):
    res = subprocess.run([sys.executable, "-m", "slamreloc.cli", "map", str(scene_dir), "--out",
                          str(tmp_path / "m"), "--precision", "fp16"], capture_output=True,
                         text=True)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert not (tmp_path / "m").exists()
