"""The default paths of every stage, declared once: the stage's command line (`python -m stages.<name> --<key>`,
key with `-` for `_`) and its work function's defaults take them from here, and tests/test_stage_paths.py checks
them against dvc.yaml. A plain data module (no imports), so that check stays fast.
"""

from __future__ import annotations

SOURCE_RAW = "data/source/raw.zarr"
SOURCE_TRAJECTORIES = "data/source/trajectories.zarr"
EXPANDED_TRAJECTORIES = "data/expanded/trajectories.zarr"
SOURCE_FRAMES = "data/rendered/source.zarr"
EXPANDED_FRAMES = "data/rendered/expanded.zarr"
METRICS = "reports/metrics.json"

SIMULATE = {"out": SOURCE_RAW, "report": "reports/simulate.json", "memory": "data/agent/memory.json"}
VALIDATE = {"raw": SOURCE_RAW, "out": SOURCE_TRAJECTORIES, "report": "reports/validate.json"}
TRAIN = {"store": SOURCE_TRAJECTORIES, "out": "models/worldcontact", "report": "reports/train.json",
         "curves": "reports/train_loss.csv"}
TRAIN_BASELINES = {"store": SOURCE_TRAJECTORIES, "out": "models/baselines", "report": "reports/train_baselines.json"}
EVALUATE = {"store": SOURCE_TRAJECTORIES, "metrics": METRICS, "stability_csv": "reports/stability.csv",
            "stability_png": "reports/stability.png"}
STRESS = {"store": "data/stress/trajectories.zarr", "metrics": METRICS, "csv": "reports/stress.csv",
          "png": "reports/stress.png", "curves": "reports/stress_curves.csv", "report": "reports/stress.json",
          "video": "reports/stress_video.mp4", "sheet": "reports/stress_side_by_side.png"}
EXPAND = {"model": "models/worldcontact", "store": SOURCE_TRAJECTORIES, "out": EXPANDED_TRAJECTORIES,
          "report": "reports/expand.json", "rejected_out": "data/expanded/rejected.zarr"}
TEACHER_CHECK = {"store": EXPANDED_TRAJECTORIES, "report": "reports/teacher_check.json",
                 "rejected": "data/expanded/rejected.zarr"}
RENDER = {"report": "reports/render.json", "sheet": "reports/render_contact_sheet.png"}
RENDER_PAIRS = ((SOURCE_TRAJECTORIES, SOURCE_FRAMES), (EXPANDED_TRAJECTORIES, EXPANDED_FRAMES))  # --inputs/--outs
DATASET = {"source_trajectories": SOURCE_TRAJECTORIES, "source_frames": SOURCE_FRAMES,
           "expanded_trajectories": EXPANDED_TRAJECTORIES, "expanded_frames": EXPANDED_FRAMES, "out": "data/lerobot",
           "report": "reports/dataset.json"}
FINETUNE = {"data_root": "data/lerobot", "out_root": "models/policy", "report": "reports/finetune.json"}
POLICY_EVAL = {"models_root": "models/policy", "report": "reports/policy.json", "videos": "reports/policy_videos",
               "table": "reports/policy_success.csv", "metrics": "reports/policy_success.json",
               "plot": "reports/policy_success.png"}
SUMMARY = {"reports": "reports", "headline": "reports/headline.json", "results": "reports/RESULTS.md"}

STAGES: dict[str, dict[str, str]] = {
    "simulate": SIMULATE, "validate": VALIDATE, "train": TRAIN, "train_baselines": TRAIN_BASELINES,
    "evaluate": EVALUATE, "stress": STRESS, "expand": EXPAND, "teacher_check": TEACHER_CHECK, "render": RENDER,
    "dataset": DATASET, "finetune": FINETUNE, "policy_eval": POLICY_EVAL, "summary": SUMMARY,
}
