"""Ahead-of-time CUDA kernels (wc/sim/cuda_kernels.py): launches are recorded with their block sizes, the variants
follow them and the extra rules, and a recorded module compiles to the cubin a GPU run of it would look up."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from wc.sim.cuda_kernels import compile_variants, keep_cuda_only, module_variants, recorded_launches


@wp.kernel(module="unique")
def _double(a: wp.array(dtype=float)):
    i = wp.tid()
    a[i] = a[i] * 2.0


def test_launches_are_recorded_with_their_block_sizes_and_restored():
    a = wp.array(np.ones(4, np.float32), device="cpu")
    original = wp.launch
    with recorded_launches() as launched:
        wp.launch(_double, dim=4, inputs=[a], device="cpu")
        wp.launch(_double, dim=4, inputs=[a], device="cpu", block_dim=64)
    assert wp.launch is original and np.allclose(a.numpy(), 4.0)  # the launches ran, the hook is gone
    module = _double.module
    assert launched == {(module, None), (module, 64)}
    default = module.options["block_dim"]
    assert module_variants(launched) == sorted({(module, default), (module, 64)}, key=lambda v: v[1])
    with_extra = module_variants(launched, "_double=128,nomatch=32")
    assert {b for _, b in with_extra} == {default, 64, 128}
    with pytest.raises(ValueError, match="REGEX=N"):
        module_variants(launched, "_double")


def test_a_variant_compiles_to_the_cubin_a_gpu_run_looks_up(tmp_path, monkeypatch):
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))
    module = _double.module
    name = f"{module.name} (block 128)"
    seconds = compile_variants([(module, 128)], arch=90)
    assert list(seconds) == [name] and seconds[name] != -1.0  # -1: the compile failed
    identifier = module.get_module_identifier(block_dim=128)
    cubins = list(tmp_path.glob(f"{identifier}/*.sm90.cubin"))
    assert len(cubins) == 1 and cubins[0].stat().st_size > 0
    assert 0.0 <= compile_variants([(module, 128)], arch=90)[name] < 1.0  # cached: skipped, not failed
    (tmp_path / identifier / "x.o").write_bytes(b"")
    (tmp_path / "wp_mod_abc_p1_t2").mkdir()
    keep_cuda_only(tmp_path)
    assert not (tmp_path / identifier / "x.o").exists() and not (tmp_path / "wp_mod_abc_p1_t2").exists()
    assert cubins[0].exists()
