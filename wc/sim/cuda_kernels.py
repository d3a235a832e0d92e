"""Ahead-of-time CUDA kernels: record which warp modules a run launches, at which block sizes, and compile those
variants for a GPU architecture with NVRTC on a machine without a GPU, into a kernel cache the GPU run then loads
instead of compiling (Newton's VBD self-contact modules take minutes each). Used by
scripts/gpu/precompile_cuda_kernels.py."""

from __future__ import annotations

import re
import shutil
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import wc.warp_settings  # noqa: F401  (first: kernels take warp's settings when defined)
import warp as wp
import warp._src.context as warp_context


@contextmanager
def recorded_launches() -> Iterator[set[tuple[Any, int | None]]]:
    """Within the block, every `wp.launch` adds (module, block_dim argument or None) to the yielded set."""
    launched: set[tuple[Any, int | None]] = set()
    original = warp_context.launch

    def recording(kernel, *args, block_dim: int | None = None, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        launched.add((kernel.module, block_dim))
        return original(kernel, *args, block_dim=block_dim, **kwargs)

    warp_context.launch = wp.launch = recording
    try:
        yield launched
    finally:
        warp_context.launch = wp.launch = original


def module_variants(launched: set[tuple[Any, int | None]], extra: str = "") -> list[tuple[Any, int]]:
    """(module, block size) to compile: each launched module at its launches' block sizes (None: the module's
    default) plus, for `extra` rules "REGEX=N[,REGEX=N]" whose pattern matches the module name, block size N (a
    size the GPU run picks where the CPU run did not, such as Newton's soft contacts at 128 on CUDA)."""
    rules = []
    for rule in filter(None, extra.split(",")):
        pattern, _, size = rule.rpartition("=")
        if not pattern or not size.isdigit():
            raise ValueError(f"extra block-size rule must be REGEX=N, got {rule!r}")
        rules.append((re.compile(pattern), int(size)))
    variants = set()
    for module, block_dim in launched:
        variants.add((module, block_dim or module.options["block_dim"]))
        variants.update((module, n) for pattern, n in rules if pattern.search(module.name))
    return sorted(variants, key=lambda v: (v[0].name, v[1]))


def compile_variants(variants: list[tuple[Any, int]], arch: int, threads: int = 1) -> dict[str, float]:
    """Compile each (module, block size) for sm_`arch` as CUBIN into warp's kernel cache (a variant already there is
    skipped); returns seconds per variant, -1 for one that failed (the GPU then compiles it itself)."""
    def compile_one(variant: tuple[Any, int]) -> tuple[str, float]:
        module, block_dim = variant
        t0 = time.perf_counter()
        try:
            module.get_module_hash(block_dim)
            module._compile(None, None, output_arch=arch, use_ptx=False,  # noqa: SLF001 - per-block-size AOT
                            options=module.resolve_options(wp.config, block_dim=block_dim))
        except Exception as error:  # noqa: BLE001
            print(f"  {module.name} (block {block_dim}): not compiled ({error})", flush=True)
            return f"{module.name} (block {block_dim})", -1.0
        return f"{module.name} (block {block_dim})", time.perf_counter() - t0

    seconds = {}
    with ThreadPoolExecutor(max(1, threads)) as pool:
        for name, s in pool.map(compile_one, variants):
            print(f"  {name}: {s:.1f} s", flush=True)
            seconds[name] = s
    return seconds


def keep_cuda_only(cache: Path) -> None:
    """Drop the CPU objects and killed compiles' leftovers from a kernel cache (they do not travel)."""
    for cpu_file in [*cache.rglob("*.o"), *cache.rglob("*.cpp")]:
        cpu_file.unlink()
    for partial in cache.rglob("*_p[0-9]*_t[0-9]*"):
        if partial.is_dir():
            shutil.rmtree(partial, ignore_errors=True)
