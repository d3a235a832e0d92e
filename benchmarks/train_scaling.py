"""World-model training on K processes of one host: steps/s, samples/s and scaling efficiency per K.

    python -m benchmarks.train_scaling --store data/source/trajectories.zarr --tag h200x4 [--procs 1,2,4]
        [--samples 19200] [--evals 4] [--batch 8] [--params params/gpu.yaml] [--set train.compile=true ...]
        [--out-dir reports/gpu]
    -> <out-dir>/train_scaling_<tag>.{json,md,png}: a row per K with gpus, steps_per_s, samples_per_s, efficiency and
       the validation curve at equal samples

For each K: `torchrun --nproc-per-node K -m stages.train` on the static-shape path (CUDA-graphed where the params
say so, DDP's all-reduce captured with the step) with the same per-process batch, for --samples / (K x batch) steps,
so every K trains on the same number of samples, evaluated --evals times at the same sample counts: the validation
curves should agree across K within noise (the same model quality). steps/s is the report's median step time
(warm-up excluded); samples/s = K x batch x steps/s; efficiency = samples/s(K) / (K x samples/s(1)). NVLink
multicast stays off in every process (NCCL_NVLS_ENABLE=0, TORCH_SYMM_MEM_DISABLE_MULTICAST=1,
NVSHMEM_DISABLE_NVLS=1). Without CUDA the processes use gloo on the CPU: the same code path, a check, not a speed.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from wc.config import load_section, read_params
from wc.reports import host_environment, write_report_atomic
from wc.train.config import Schedule, TrainConfig

MULTICAST_OFF = {"NCCL_NVLS_ENABLE": "0", "TORCH_SYMM_MEM_DISABLE_MULTICAST": "1", "NVSHMEM_DISABLE_NVLS": "1"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


LR_SCALES = {"none": lambda k: 1.0, "linear": float, "sqrt": lambda k: k ** 0.5}


def lr_overrides(base: Schedule, factor: float) -> list[str]:
    """--set arguments scaling the base stage's learning rates by `factor` (K processes take K x the batch)."""
    return [a for key in ("peak_lr", "start_lr", "final_lr")
            for a in ("--set", f"train.base.{key}={getattr(base, key) * factor:.6e}")]


def run_k(k: int, steps: int, args: argparse.Namespace, work: Path, device: str, base: Schedule) -> dict[str, Any]:
    """One torchrun of K processes; its train report plus the wall time."""
    report = work / f"k{k}.json"
    every = max(1, steps // args.evals)
    factor = LR_SCALES[args.lr_scale](k)
    overrides = [*[a for s in args.overrides for a in ("--set", s)],  # the benchmark's own settings win
                 "--set", f"train.device={device}", "--set", "train.static=true",
                 "--set", f"train.batch_size={args.batch}",
                 "--set", f"train.base.steps={steps}", "--set", f"train.base.warmup_steps={max(1, steps // 10)}",
                 "--set", "train.projection.steps=0", "--set", "train.projection.warmup_steps=0",
                 "--set", f"train.eval_every_steps={every}", "--set", f"train.checkpoint_every_steps={steps}",
                 *lr_overrides(base, factor)]
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", str(k), "--master-port", str(free_port()),
           "-m", "stages.train", "--params", args.params, "--store", args.store, "--out", str(work / f"model_k{k}"),
           "--report", str(report), "--curves", str(work / f"curves_k{k}.csv"), *overrides]
    env = {**os.environ, **MULTICAST_OFF, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
    log = work / f"k{k}.log"
    started = time.perf_counter()
    with log.open("w") as sink:
        try:
            code = subprocess.run(cmd, stdout=sink, stderr=subprocess.STDOUT, env=env, timeout=args.timeout).returncode
        except subprocess.TimeoutExpired:
            code = f"timed out after {args.timeout} s"
    wall = time.perf_counter() - started
    if code != 0:
        return {"gpus": k, "error": f"{code}: {log.read_text()[-3000:]}"}
    r = json.loads(report.read_text())
    steps_per_s = 1.0 / r["s_per_step_median"]
    return {"gpus": k, "processes": r["processes"], "steps": steps, "batch_per_process": args.batch,
            "lr_factor": factor,
            "steps_per_s": steps_per_s, "samples_per_s": k * args.batch * steps_per_s, "wall_s": wall,
            "val_loss_after_samples": r["history"][-1]["val_loss"], "samples": k * args.batch * steps,
            "val_curve": [{"samples": k * args.batch * h["step"], "val_loss": h["val_loss"]} for h in r["history"]]}


def markdown(report: dict[str, Any]) -> str:
    lines = [f"# World-model training scaling ({report['tag']})", "",
             f"{report['environment'].get('gpu', report['device'])}, torch {report['environment']['torch']}; "
             f"{report['samples']} samples per K, batch {report['batch']} per process; "
             f"{'CUDA-graphed' if report.get('cuda_graph') else 'eager'} static step; learning rate scaled "
             f"{report.get('lr_scale', 'none')} with K.", "",
             "| gpus | steps/s | samples/s | efficiency | val loss after the samples |", "|---|---|---|---|---|"]
    for r in report["rows"]:
        if "error" in r:
            lines.append(f"| {r['gpus']} | failed: {r['error'][-120:]!r} | | | |")
        else:
            lines.append(f"| {r['gpus']} | {r['steps_per_s']:.2f} | {r['samples_per_s']:.1f} | {r['efficiency']:.2f} | "
                         f"{r['val_loss_after_samples']:.4g} |")
    curves = [r for r in report["rows"] if "val_curve" in r]
    if curves:
        lines += ["", "Validation loss at equal samples:", "",
                  "| samples | " + " | ".join(f"K={r['gpus']}" for r in curves) + " |",
                  "|---|" + "---|" * len(curves)]
        for i, point in enumerate(curves[0]["val_curve"]):
            cells = [f"{r['val_curve'][i]['val_loss']:.4g}" if i < len(r["val_curve"]) else "" for r in curves]
            lines.append(f"| {point['samples']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def chart(report: dict[str, Any], path: Path) -> None:
    """Samples/s per K beside the ideal line, and the validation curves against samples."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in report["rows"] if "samples_per_s" in r]
    if not rows:
        return
    fig, (speed, quality) = plt.subplots(1, 2, figsize=(10, 4))
    base = next((r["samples_per_s"] for r in rows if r["gpus"] == 1), rows[0]["samples_per_s"] / rows[0]["gpus"])
    ks = [r["gpus"] for r in rows]
    speed.plot(ks, [r["samples_per_s"] for r in rows], "o-", label="measured")
    speed.plot(ks, [k * base for k in ks], "--", color="grey", label="K x one process")
    speed.set(xlabel="processes (GPUs)", ylabel="samples/s", xticks=ks, title="training throughput")
    speed.legend()
    for r in rows:
        quality.plot([p["samples"] for p in r["val_curve"]], [p["val_loss"] for p in r["val_curve"]], "o-",
                     label=f"K={r['gpus']}")
    quality.set(xlabel="samples", ylabel="validation loss", yscale="log", title="the same samples, the same model?")
    quality.legend()
    fig.suptitle(f"World-model training on K processes ({report['tag']})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--store", default="data/source/trajectories.zarr")
    parser.add_argument("--procs", default=None, help="comma-separated K (default 1, 2, 4, ... up to the GPU count)")
    parser.add_argument("--samples", type=int, default=19200)
    parser.add_argument("--evals", type=int, default=4, help="validations per run, at the same sample counts per K")
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--lr-scale", choices=sorted(LR_SCALES), default="linear",
                        help="the base learning rates at K processes (K x the batch): x K, x sqrt(K) or unchanged")
    parser.add_argument("--timeout", type=float, default=900, help="seconds one K may take (its row says so)")
    parser.add_argument("--tag", default="cpu")
    parser.add_argument("--out-dir", default="reports/gpu")
    args = parser.parse_args(argv)
    gpus = torch.cuda.device_count()
    train_cfg = load_section(read_params(args.params, [*args.overrides, "train.static=true"]), "train", TrainConfig)
    device = "cuda" if gpus else "cpu"
    ks = ([int(k) for k in args.procs.split(",")] if args.procs
          else [k for k in (1, 2, 4, 8) if k <= max(gpus, 2)])
    if gpus and max(ks) > gpus:
        raise SystemExit(f"train_scaling: asked for {max(ks)} processes, the machine has {gpus} GPUs")
    work = Path(tempfile.mkdtemp(prefix="train_scaling_"))
    report: dict[str, Any] = {"tag": args.tag, "device": device, "samples": args.samples, "batch": args.batch,
                              "environment": host_environment(device, gpus), "multicast_off": MULTICAST_OFF, "rows": [],
                              "cuda_graph": bool(gpus) and train_cfg.cuda_graph, "lr_scale": args.lr_scale}
    out = Path(args.out_dir) / f"train_scaling_{args.tag}.json"
    for k in ks:
        row = run_k(k, max(1, args.samples // (k * args.batch)), args, work, device, train_cfg.base)
        base = next((r for r in report["rows"] if r.get("gpus") == 1 and "samples_per_s" in r), row)
        if "samples_per_s" in row and "samples_per_s" in base:
            row["efficiency"] = row["samples_per_s"] / (k * base["samples_per_s"])
        report["rows"].append(row)
        write_report_atomic(out, report, markdown(report))
        chart(report, out.with_suffix(".png"))
        print(markdown(report), flush=True)


if __name__ == "__main__":
    main()
