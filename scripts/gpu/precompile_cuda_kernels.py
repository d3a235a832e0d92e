"""Compile the warp/Newton CUDA kernels a stage needs on this CPU machine (NVRTC needs no GPU), into a kernel cache
that travels to the bare GPU machine: there Newton's VBD self-contact modules alone took 6.5 min
(`soft_edge_contacts`) and over 5 min (`soft_face_contacts`) to compile, before the first solver step.

    python scripts/gpu/precompile_cuda_kernels.py --cache .carry/warp_cache [--arch 90] \
        [--params params.yaml] [--set sim.worlds=2 ...] [--task lift_handle]

It runs one small simulate batch of the task on the CPU (which registers and loads every module the stage uses,
with the kernel hashes the GPU run computes: same source, options and block size), then compiles each loaded module
for the CUDA architecture into `--cache`/<warp version>/ and drops the CPU objects there. On the GPU machine:
WARP_CACHE_PATH=<that folder> (warp.config.kernel_cache_dir) before warp initialises; a module the CPU run did not
load (a CUDA-only path) still compiles there on first use.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cache", required=True, help="kernel cache folder to fill (warp.config.kernel_cache_dir)")
    parser.add_argument("--arch", type=int, default=90, help="CUDA compute capability: 90 = H100 / H200")
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--task", default="lift_handle")
    parser.add_argument("--extra-block-dims", default="soft_(edge|face)_contacts=128", metavar="REGEX=N[,REGEX=N]",
                        help="block sizes the GPU run launches with beside the CPU run's (Newton's soft contacts: 128 "
                             "on CUDA)")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1, help="modules compiled at once")
    args = parser.parse_args()

    import warp as wp

    wp.config.kernel_cache_dir = str(Path(args.cache).resolve())
    wp.init()
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    from wc.sim.cuda_kernels import compile_variants, keep_cuda_only, module_variants, recorded_launches

    with recorded_launches() as launched:
        run_cpu_batch(args.params, args.overrides, args.task)
    variants = module_variants(launched, args.extra_block_dims)
    print(f"compiling {len(variants)} module variants for sm_{args.arch} ...", flush=True)
    compile_variants(variants, args.arch, args.threads)
    cache = Path(wp.config.kernel_cache_dir)
    keep_cuda_only(cache)
    cubins = list(cache.rglob(f"*.sm{args.arch}.cubin"))
    print(f"{len(cubins)} cubins in {cache} ({sum(f.stat().st_size for f in cubins) / 2**20:.1f} MiB)")


def run_cpu_batch(params_path: str, overrides: list[str], task: str) -> None:
    """One simulate batch of `task` on the CPU (two worlds, two episodes), written to a throwaway store."""
    from stages.simulate import main as simulate

    with tempfile.TemporaryDirectory() as tmp:
        simulate(["--params", params_path, *[a for o in overrides for a in ("--set", o)],
                  "--set", "sim.device=cpu", "--set", "validate.device=cpu", "--set", "sim.worlds=2",
                  "--set", "agent.workers=1", "--set", f"agent.tasks=[{task}]", "--set", "agent.episodes_per_task=1",
                  "--set", "agent.max_attempts_per_task=2", "--out", f"{tmp}/raw.zarr",
                  "--report", f"{tmp}/simulate.json", "--memory", f"{tmp}/memory.json"])


if __name__ == "__main__":
    main()
