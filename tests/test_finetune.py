"""Stage `finetune` on a tiny LeRobot dataset built here, training through lerobot's own `train()`: ACT trains,
saves and reloads; both datasets train identically; the pi0.5 path runs one real step from a tiny local
checkpoint and tokenizer; missing pretrained files fail loudly; the stock `lerobot-train` CLI runs offline."""

from __future__ import annotations

import copy
import dataclasses
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import yaml
from lerobot.datasets import LeRobotDataset

from benchmarks import policy_placement
from tests.stage_run import assert_one_line_error, run_stage
from wc.policy.finetune_stage import arm_gpus, run, stage_params
from wc.config import ParamsError, load_section
from wc.policy.comparison import FLAG
from wc.policy.finetune import dataset_metadata, finetune, load_policy, policy_config
from wc.policy.policy_config import PolicyConfig
from wc.policy.pretrained import PretrainedFilesError
from wc.policy.processors import make_pi05_processors
from wc.policy.stock_trainer import StepRecorder

TASK = "right grasp and lift"
H = W = 32
EPISODES, FRAMES = 2, 10
ACT = dict(type="act", datasets=["source", "expanded"], task=TASK, cameras=["top", "wrist"], steps=3, batch_size=4,
           lr=1.0e-3, betas=[0.9, 0.999], eps=1.0e-8, weight_decay=1.0e-4, grad_clip_norm=10.0, warmup_steps=0,
           decay_steps=100, decay_lr=1.0e-4, chunk_size=4, n_action_steps=4, device="cpu", seed=0, log_every_steps=1,
           config=dict(pretrained_backbone_weights=None, dim_model=32, n_heads=2, dim_feedforward=64,
                       n_encoder_layers=1, n_vae_encoder_layers=1, latent_dim=8, dropout=0.0))
PI05 = dict(ACT, type="pi05", steps=1, batch_size=2, lr=2.5e-5, betas=[0.9, 0.95], weight_decay=1.0e-2,
            grad_clip_norm=1.0, warmup_steps=1000, decay_steps=30000, decay_lr=2.5e-6,
            normalization={"VISUAL": "IDENTITY", "STATE": "QUANTILES", "ACTION": "QUANTILES"},
            config=dict(image_resolution=[H, W], tokenizer_max_length=48, max_state_dim=8, max_action_dim=8,
                        dtype="float32"))


def _cfg(base: dict[str, Any], **changes: Any) -> PolicyConfig:
    return load_section({"policy": {**copy.deepcopy(base), **changes}, "_source": "test"}, "policy", PolicyConfig)


@pytest.fixture(scope="module")
def data_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """data/lerobot/{source,expanded}: the same 2 episodes x 10 frames of two 32x32 videos, 7-D state and action."""
    root = tmp_path_factory.mktemp("lerobot")
    image = {"dtype": "video", "shape": (H, W, 3), "names": ["height", "width", "channels"]}
    vector = {"dtype": "float32", "shape": (7,), "names": [f"j{i}" for i in range(7)]}
    features = {"observation.images.top": image, "observation.images.wrist": dict(image),
                "observation.state": vector, "action": dict(vector)}
    ds = LeRobotDataset.create("test/source", fps=25, features=features, root=root / "source", use_videos=True)
    rng = np.random.default_rng(0)
    for episode in range(EPISODES):
        state = np.cumsum(rng.normal(0, 0.05, (FRAMES + 1, 7)), axis=0).astype(np.float32)
        for k in range(FRAMES):
            ds.add_frame({"observation.images.top": rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
                          "observation.images.wrist": rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
                          "observation.state": state[k], "action": state[k + 1], "task": TASK})
        ds.save_episode(parallel_encoding=False)
    ds.finalize()
    shutil.copytree(root / "source", root / "expanded")
    return root


def _actions(policy: Any, preprocessor: Any, postprocessor: Any, batch: dict[str, Any]) -> torch.Tensor:
    policy.eval()
    torch.manual_seed(0)  # pi0.5 samples its denoising noise
    with torch.no_grad():
        return postprocessor(policy.predict_action_chunk(preprocessor(copy.copy(batch))))


def _batch(root: Path, size: int) -> dict[str, Any]:
    """The first `size` frames of the dataset at `root` as one batch (observations for inference)."""
    dataset = LeRobotDataset("test/batch", root=root, delta_timestamps={"action": [0.0]})
    return next(iter(torch.utils.data.DataLoader(dataset, batch_size=size)))


def _capture_policy(monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """Keep the policy lerobot's train() hands to our accelerator: the very module it trains."""
    seen: dict[str, Any] = {}
    prepare = StepRecorder.prepare

    def capture(self: StepRecorder, *args: Any, **kwargs: Any) -> Any:
        seen["policy"] = args[0]
        return prepare(self, *args, **kwargs)

    monkeypatch.setattr(StepRecorder, "prepare", capture)
    return seen


@pytest.mark.slow
def test_act_trains_with_lerobot_train_and_reloads_identically(data_root: Path, tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    seen = _capture_policy(monkeypatch)
    cfg = _cfg(ACT, steps=7, log_every_steps=2)
    summary = finetune(data_root / "source", tmp_path / "policy", cfg)
    # losses of every step from lerobot's own update, averaged per log window (the last one shorter)
    assert [h["step"] for h in summary["history"]] == [2, 4, 6, 7]
    assert summary["final_loss"] < 0.8 * summary["first_loss"] and np.isfinite(summary["final_loss"])
    lrs = [h["lr"] for h in summary["history"]]
    assert lrs == sorted(lrs, reverse=True) and lrs[0] <= cfg.lr  # cosine decay from the params, not ACT's preset
    assert summary["trainer"] == "lerobot-train 0.6.1" and summary["parameters"] > 0
    assert summary["s_per_step_median"] > 0 and summary["train_s"] >= summary["s_per_step_median"]
    saved = {p.name for p in (tmp_path / "policy").iterdir()}
    assert {"config.json", "model.safetensors", "train_config.json", "policy_preprocessor.json",
            "policy_postprocessor.json", "train_summary.json"} <= saved
    assert [p.name for p in tmp_path.iterdir()] == ["policy"]  # no temporary or lerobot run directory left
    train_cfg = json.loads((tmp_path / "policy" / "train_config.json").read_text())
    assert (train_cfg["steps"], train_cfg["seed"], train_cfg["use_policy_training_preset"]) == (7, 0, False)
    assert train_cfg["scheduler"]["type"] == "cosine_decay_with_warmup" and train_cfg["wandb"]["enable"] is False
    batch = _batch(data_root / "source", cfg.batch_size)
    policy, preprocessor, postprocessor = load_policy(tmp_path / "policy")
    actions = _actions(policy, preprocessor, postprocessor, batch)
    assert actions.shape == (cfg.batch_size, cfg.chunk_size, 7)
    expected = _actions(seen["policy"], preprocessor, postprocessor, batch)  # the policy as training left it
    torch.testing.assert_close(actions, expected, rtol=0, atol=0)


@pytest.mark.slow
def test_stage_trains_both_datasets_with_identical_settings(data_root: Path, tmp_path: Path) -> None:
    params = {"policy": copy.deepcopy(ACT), "_source": "test"}
    report = run(params, data_root, tmp_path / "models", tmp_path / "finetune.json")
    saved = json.loads((tmp_path / "finetune.json").read_text())
    assert saved["params_hash"] == report["params_hash"] and saved["steps"] == ACT["steps"]
    src, exp = saved["datasets"]["source"], saved["datasets"]["expanded"]
    assert np.isfinite(src["final_loss"]) and src["s_per_step_median"] > 0
    # the two datasets are copies here: same settings and seed must give the same run, bit for bit
    assert src["final_loss"] == exp["final_loss"]
    assert saved[FLAG] is True  # copies: the report says the comparison compares nothing
    weights = [(tmp_path / "models" / n / "model.safetensors").read_bytes() for n in ("source", "expanded")]
    assert weights[0] == weights[1]
    summary = json.loads((tmp_path / "models" / "source" / "train_summary.json").read_text())
    assert summary["params_hash"] == report["params_hash"] and len(summary["history"]) == ACT["steps"]


@pytest.mark.slow
def test_side_by_side_trains_each_dataset_in_its_own_process_to_the_same_policy(data_root: Path,
                                                                               tmp_path: Path) -> None:
    params = {"policy": {**copy.deepcopy(ACT), "side_by_side": True}, "_source": "test"}
    saved = run(params, data_root, tmp_path / "models", tmp_path / "finetune.json")
    src, exp = saved["datasets"]["source"], saved["datasets"]["expanded"]
    weights = [(tmp_path / "models" / n / "model.safetensors").read_bytes() for n in ("source", "expanded")]
    assert weights[0] == weights[1] and src["final_loss"] == exp["final_loss"]  # copies, same seed: same policy
    alone = finetune(data_root / "source", tmp_path / "alone", _cfg(ACT))  # the same training in this process
    assert src["final_loss"] == pytest.approx(alone["final_loss"], rel=1e-4)
    assert os.getpid() not in {src["pid"], exp["pid"]} and src["pid"] != exp["pid"]
    assert src["gpu"] is None and exp["gpu"] is None  # on the CPU: no GPU of its own


def test_side_by_side_policies_take_a_gpu_each_where_there_are_several() -> None:
    assert arm_gpus(3, "cuda", ["0", "1"]) == ["0", "1", "0"]
    assert arm_gpus(2, "cuda", ["3", "5", "6", "7"]) == ["3", "5"]
    assert arm_gpus(2, "cuda", ["0"]) == [None, None]  # one GPU: shared, as configured
    assert arm_gpus(2, "cpu", ["0", "1"]) == [None, None]
    assert arm_gpus(2, "cuda:1", ["0", "1"]) == [None, None]  # an explicit device is kept


def test_clear_errors(data_root: Path, tmp_path: Path) -> None:
    empty = tmp_path / "checkpoint"
    empty.mkdir()
    with pytest.raises(PretrainedFilesError, match="model.safetensors"):
        finetune(data_root / "source", tmp_path / "policy", _cfg(ACT, pretrained_path=str(empty)))
    with pytest.raises(PretrainedFilesError, match="tokenizer_path"):
        finetune(data_root / "source", tmp_path / "policy", _cfg(PI05, tokenizer_path=str(tmp_path / "no_tokenizer")))
    with pytest.raises(ParamsError, match="tokenizer_path"):
        _cfg(PI05)
    with pytest.raises(ValueError, match="policy.config.bogus"):
        policy_config(_cfg(ACT, config={"bogus": 1}), dataset_metadata(data_root / "source", _cfg(ACT)))
    with pytest.raises(ValueError, match="optimizer_lr_backbone .* must equal policy.lr"):
        policy_config(_cfg(ACT, config=dict(ACT["config"], optimizer_lr_backbone=1e-5)),
                      dataset_metadata(data_root / "source", _cfg(ACT)))
    with pytest.raises(ParamsError, match="policy.config.device"):
        _cfg(ACT, config={"device": "cuda"})
    with pytest.raises(ValueError, match="expected only policy.task"):
        dataset_metadata(data_root / "source", _cfg(ACT, task="left grasp"))
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="not a saved policy"):  # refused before training
        finetune(data_root / "source", tmp_path / "notes", _cfg(ACT))
    with pytest.raises(FileNotFoundError, match="run the dataset stage"):
        run({"policy": dict(ACT, datasets=["nowhere"]), "_source": "test"}, data_root, tmp_path, tmp_path / "r.json")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint", "notes"]  # nothing half-written


@pytest.mark.slow
def test_stock_lerobot_train_cli_runs_offline(data_root: Path, tmp_path: Path) -> None:
    """The documented command: lerobot's own CLI on our dataset, 2 steps, no network; load_policy reads its output."""
    cli = Path(sys.executable).with_name("lerobot-train")
    args = [str(cli), "--dataset.repo_id=worldcontact/source", f"--dataset.root={data_root / 'source'}",
            "--dataset.video_backend=pyav", "--dataset.use_imagenet_stats=false", "--policy.type=act",
            "--policy.device=cpu", "--policy.push_to_hub=false", "--policy.pretrained_backbone_weights=null",
            "--policy.chunk_size=4", "--policy.n_action_steps=4", "--policy.dim_model=32", "--policy.n_heads=2",
            "--policy.dim_feedforward=64", "--policy.n_encoder_layers=1", "--policy.n_vae_encoder_layers=1",
            "--use_policy_training_preset=false", "--optimizer.type=adamw", "--optimizer.lr=1e-4",
            "--optimizer.weight_decay=1e-4", "--scheduler.type=cosine_decay_with_warmup",
            "--scheduler.num_warmup_steps=0", "--scheduler.num_decay_steps=100", "--scheduler.peak_lr=1e-4",
            "--scheduler.decay_lr=1e-5", "--steps=2", "--batch_size=4", "--seed=0", "--num_workers=0",
            "--log_freq=1", "--wandb.enable=false", f"--output_dir={tmp_path / 'run'}"]
    env = dict(os.environ, HF_HUB_OFFLINE="1", HF_DATASETS_OFFLINE="1", WANDB_MODE="disabled")
    result = subprocess.run(args, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    model = tmp_path / "run" / "checkpoints" / "last" / "pretrained_model"
    assert json.loads((model / "train_config.json").read_text())["steps"] == 2
    policy, preprocessor, postprocessor = load_policy(model)
    actions = _actions(policy, preprocessor, postprocessor, _batch(data_root / "source", 2))
    assert actions.shape == (2, 4, 7) and torch.isfinite(actions).all()


@pytest.mark.slow
def test_stage_names_a_corrupt_info_json(data_root: Path, tmp_path: Path) -> None:
    """`python -m stages.finetune` with the expanded dataset's meta/info.json cut short by a bad edit: status 2 and
    one line naming that file and where its JSON breaks, before the source dataset trains."""
    root = tmp_path / "lerobot"
    shutil.copytree(data_root, root)
    info = root / "expanded" / "meta" / "info.json"
    info.write_text("{\n  codebase_version: 3\n}\n")  # an unquoted key
    out = tmp_path / "policy"
    done = run_stage("finetune", "--data-root", str(root), "--out-root", str(out), "--report", str(tmp_path / "r.json"))
    assert_one_line_error(done, "finetune", str(info), "not valid JSON",
                          "Expecting property name enclosed in double quotes", "line 2 column 3", progress=True)
    assert not out.exists()


def test_policy_fragment_replaces_the_section(tmp_path: Path) -> None:
    (tmp_path / "params.yaml").write_text("other: {a: 1}\npolicy: {type: act}\n")
    params = stage_params(tmp_path / "params.yaml", ["policy.steps=7", "other.a=2"], "params/policy_pi05.yaml")
    cfg = load_section(params, "policy", PolicyConfig)
    assert (cfg.type, cfg.steps, params["other"]["a"]) == ("pi05", 7, 2)
    assert (cfg.lr, cfg.betas, cfg.eps, cfg.weight_decay) == (2.5e-5, (0.9, 0.95), 1e-8, 1e-2)
    assert (cfg.warmup_steps, cfg.decay_steps, cfg.decay_lr, cfg.chunk_size) == (1000, 30000, 2.5e-6, 50)
    assert cfg.normalization == {"VISUAL": "IDENTITY", "STATE": "QUANTILES", "ACTION": "QUANTILES"}
    gpu = load_section(stage_params(tmp_path / "params.yaml", [], "params/policy_act_gpu.yaml"), "policy", PolicyConfig)
    assert gpu.type == "act" and gpu.device == "cuda" and gpu.config["pretrained_backbone_weights"] is None


# --- pi0.5: a tiny randomly initialised model through the real path ---------------------------------------------

@pytest.fixture
def tiny_pi05(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    """Shrink lerobot's PaliGemma / Gemma sizes (8 heads: lerobot's joint attention hard-codes them) and the
    SigLIP tower; returns a tiny word-level tokenizer saved offline."""
    from lerobot.policies.pi05 import modeling_pi05
    from tokenizers import Tokenizer, models, pre_tokenizers
    from transformers import PreTrainedTokenizerFast

    def tiny_gemma(variant: str) -> Any:
        return modeling_pi05.GemmaConfig(width=32, depth=1, mlp_dim=64, num_heads=8, num_kv_heads=1, head_dim=4)

    paligemma = modeling_pi05.PaliGemmaForConditionalGenerationWithPiGemma

    def tiny_paligemma(config: Any) -> Any:
        vision = config.vision_config
        vision.hidden_size, vision.intermediate_size, vision.num_hidden_layers = 32, 64, 1
        vision.num_attention_heads, vision.patch_size = 2, 8
        vision.projection_dim = config.text_config.hidden_size
        return paligemma(config)

    monkeypatch.setattr(modeling_pi05, "get_gemma_config", tiny_gemma)
    monkeypatch.setattr(modeling_pi05, "PaliGemmaForConditionalGenerationWithPiGemma", tiny_paligemma)
    words = ["<pad>", "<unk>", "<bos>", "<eos>", "Task:", "State:", "Action:", *TASK.split(), ";"]
    vocab = {w: i for i, w in enumerate(words + [str(i) for i in range(256)])}
    tokenizer = Tokenizer(models.WordLevel(vocab, unk_token="<unk>"))
    tokenizer.pre_tokenizer = pre_tokenizers.WhitespaceSplit()
    PreTrainedTokenizerFast(tokenizer_object=tokenizer, pad_token="<pad>", unk_token="<unk>", bos_token="<bos>",
                            eos_token="<eos>").save_pretrained(tmp_path / "tokenizer")
    return tmp_path / "tokenizer"


def _checkpoint(path: Path, cfg: PolicyConfig, root: Path) -> Path:
    """A local pi0.5 checkpoint (config.json + model.safetensors) of a randomly initialised policy."""
    from lerobot.policies import make_policy

    meta = dataset_metadata(root, cfg)
    make_policy(policy_config(cfg, meta), ds_meta=meta).save_pretrained(path)
    return path


@pytest.mark.slow
def test_pi05_one_training_step_from_a_local_checkpoint(data_root: Path, tiny_pi05: Path, tmp_path: Path) -> None:
    cfg = _cfg(PI05, tokenizer_path=str(tiny_pi05))
    with pytest.raises(PretrainedFilesError, match="pretrained_path is not set"):
        finetune(data_root / "source", tmp_path / "policy", cfg)
    checkpoint = _checkpoint(tmp_path / "pi05_base", cfg, data_root / "source")
    cfg = dataclasses.replace(cfg, pretrained_path=str(checkpoint))
    summary = finetune(data_root / "source", tmp_path / "policy", cfg)
    assert summary["steps"] == 1 and np.isfinite(summary["final_loss"])
    assert (tmp_path / "policy" / "tokenizer" / "tokenizer.json").is_file()
    saved = json.loads((tmp_path / "policy" / "config.json").read_text())
    assert (saved["type"], saved["chunk_size"], saved["optimizer_betas"]) == ("pi05", 4, [0.9, 0.95])
    assert saved["scheduler_warmup_steps"] == 1000 and saved["normalization_mapping"]["STATE"] == "QUANTILES"
    assert saved["pretrained_path"] == str(checkpoint)  # where training started, not lerobot's temporary copy
    policy, preprocessor, postprocessor = load_policy(tmp_path / "policy")
    actions = _actions(policy, preprocessor, postprocessor, _batch(data_root / "source", cfg.batch_size))
    assert actions.shape == (cfg.batch_size, cfg.chunk_size, 7) and torch.isfinite(actions).all()
    # a checkpoint whose tensors do not fit the config: lerobot would silently keep random weights
    mismatched = _cfg(PI05, tokenizer_path=str(tiny_pi05), config=dict(PI05["config"], max_action_dim=16))
    _checkpoint(tmp_path / "other", mismatched, data_root / "source")
    with pytest.raises(PretrainedFilesError, match="not loaded"):
        finetune(data_root / "source", tmp_path / "policy2", dataclasses.replace(cfg, pretrained_path=str(tmp_path / "other")))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other", "pi05_base", "policy", "tokenizer"]


def test_pi05_processors_match_lerobots_factory(data_root: Path, tiny_pi05: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """Ours differ from lerobot 0.6.1's make_pi05_pre_post_processors only in where the tokenizer comes from."""
    from lerobot.policies.pi05 import processor_pi05
    from lerobot.processor import TokenizerProcessorStep

    def local_tokenizer(**kwargs: Any) -> TokenizerProcessorStep:
        return TokenizerProcessorStep(**{**kwargs, "tokenizer_name": str(tiny_pi05)})

    monkeypatch.setattr(processor_pi05, "TokenizerProcessorStep", local_tokenizer)
    cfg = _cfg(PI05, tokenizer_path=str(tiny_pi05))
    meta = dataset_metadata(data_root / "source", cfg)
    config = policy_config(cfg, meta)
    ours = make_pi05_processors(config, meta.stats, tiny_pi05)
    theirs = processor_pi05.make_pi05_pre_post_processors(config, meta.stats)
    for a, b in zip(ours, theirs, strict=True):
        assert [type(s) for s in a.steps] == [type(s) for s in b.steps]
        assert [s.get_config() for s in a.steps] == [s.get_config() for s in b.steps]


@pytest.mark.slow
def test_placement_benchmark_times_both_schedules_of_the_same_training(data_root: Path, tmp_path: Path) -> None:
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump({"policy": ACT}))
    report = policy_placement.main(["--params", str(params), "--data-root", str(data_root), "--tag", "test",
                                    "--out-dir", str(tmp_path / "reports")])
    rows = {r["schedule"]: r for r in report["rows"]}
    assert list(rows) == ["one_after_another", "side_by_side"] and rows["one_after_another"]["speedup"] == 1.0
    losses = {name: [a["final_loss"] for a in r["arms"].values()] for name, r in rows.items()}
    assert losses["side_by_side"] == pytest.approx(losses["one_after_another"], rel=1e-4)  # placement only
    assert rows["side_by_side"]["speedup"] == pytest.approx(rows["one_after_another"]["wall_s"]
                                                            / rows["side_by_side"]["wall_s"])
    assert json.loads((tmp_path / "reports" / "policy_placement_test.json").read_text())["rows"] == report["rows"]
    assert "| side_by_side |" in (tmp_path / "reports" / "policy_placement_test.md").read_text()
    with pytest.raises(SystemExit, match="unknown schedule"):
        policy_placement.main(["--params", str(params), "--schedules", "all_at_once"])
