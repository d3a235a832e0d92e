"""Stage `finetune` on a tiny LeRobot dataset built here: ACT trains, saves and reloads; both datasets
train identically; the pi0.5 path runs one real step from a tiny local checkpoint and tokenizer;
missing pretrained files fail loudly."""

from __future__ import annotations

import copy
import dataclasses
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from lerobot.datasets import LeRobotDataset

from stages.finetune import run, stage_params
from wc.config import ParamsError, load_section
from wc.policy.comparison import FLAG
from wc.policy.finetune import (batches, build_trainer, dataset_metadata, finetune, load_policy, policy_config,
                                save_policy, train_step)
from wc.policy.policy_config import PolicyConfig
from wc.policy.pretrained import PretrainedFilesError
from wc.policy.processors import make_pi05_processors

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


def test_act_loss_decreases_on_a_fixed_batch(data_root: Path) -> None:
    trainer = build_trainer(data_root / "source", _cfg(ACT))
    batch = trainer.preprocessor(next(batches(trainer.dataset, trainer.meta, trainer.cfg)))
    losses = [train_step(trainer.policy, batch, trainer.optimizer, trainer.scheduler, 10.0) for _ in range(6)]
    assert all(np.isfinite(losses))
    assert np.mean(losses[-2:]) < 0.8 * np.mean(losses[:2])


def test_act_saved_policy_reloads_with_identical_actions(data_root: Path, tmp_path: Path) -> None:
    trainer = build_trainer(data_root / "source", _cfg(ACT))
    data = batches(trainer.dataset, trainer.meta, trainer.cfg)
    for _ in range(2):
        train_step(trainer.policy, trainer.preprocessor(next(data)), trainer.optimizer, trainer.scheduler, 10.0)
    save_policy(trainer, tmp_path / "policy", {"steps": 2})
    assert {"config.json", "model.safetensors", "policy_preprocessor.json", "policy_postprocessor.json",
            "train_summary.json"} <= {p.name for p in (tmp_path / "policy").iterdir()}
    batch = next(data)
    expected = _actions(trainer.policy, trainer.preprocessor, trainer.postprocessor, batch)
    actions = _actions(*load_policy(tmp_path / "policy"), batch)
    assert actions.shape == (trainer.cfg.batch_size, trainer.cfg.chunk_size, 7)
    torch.testing.assert_close(actions, expected, rtol=0, atol=1e-6)
    assert not any(p.name.startswith(".policy.") for p in tmp_path.iterdir())  # no temporary left behind


def test_stage_trains_both_datasets_with_identical_settings(data_root: Path, tmp_path: Path) -> None:
    params = {"policy": copy.deepcopy(ACT), "_source": "test"}
    report = run(params, data_root, tmp_path / "models", tmp_path / "finetune.json", progress=False)
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


def test_clear_errors(data_root: Path, tmp_path: Path) -> None:
    empty = tmp_path / "checkpoint"
    empty.mkdir()
    with pytest.raises(PretrainedFilesError, match="model.safetensors"):
        build_trainer(data_root / "source", _cfg(ACT, pretrained_path=str(empty)))
    with pytest.raises(PretrainedFilesError, match="tokenizer_path"):
        build_trainer(data_root / "source", _cfg(PI05, tokenizer_path=str(tmp_path / "no_tokenizer")))
    with pytest.raises(ParamsError, match="tokenizer_path"):
        _cfg(PI05)
    with pytest.raises(ValueError, match="policy.config.bogus"):
        policy_config(_cfg(ACT, config={"bogus": 1}), dataset_metadata(data_root / "source", _cfg(ACT)))
    with pytest.raises(ParamsError, match="policy.config.device"):
        _cfg(ACT, config={"device": "cuda"})
    with pytest.raises(ValueError, match="expected only policy.task"):
        dataset_metadata(data_root / "source", _cfg(ACT, task="left grasp"))
    with pytest.raises(FileNotFoundError, match="run the dataset stage"):
        run({"policy": dict(ACT, datasets=["nowhere"]), "_source": "test"}, data_root, tmp_path, tmp_path / "r.json")


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


def test_pi05_one_training_step_from_a_local_checkpoint(data_root: Path, tiny_pi05: Path, tmp_path: Path) -> None:
    cfg = _cfg(PI05, tokenizer_path=str(tiny_pi05))
    checkpoint = _checkpoint(tmp_path / "pi05_base", cfg, data_root / "source")
    cfg = dataclasses.replace(cfg, pretrained_path=str(checkpoint))
    summary = finetune(data_root / "source", tmp_path / "policy", cfg, progress=False)
    assert summary["steps"] == 1 and np.isfinite(summary["final_loss"])
    assert (tmp_path / "policy" / "tokenizer" / "tokenizer.json").is_file()
    saved = json.loads((tmp_path / "policy" / "config.json").read_text())
    assert (saved["type"], saved["chunk_size"], saved["optimizer_betas"]) == ("pi05", 4, [0.9, 0.95])
    assert saved["scheduler_warmup_steps"] == 1000 and saved["normalization_mapping"]["STATE"] == "QUANTILES"
    policy, preprocessor, postprocessor = load_policy(tmp_path / "policy")
    batch = next(batches(LeRobotDataset("t", root=data_root / "source", delta_timestamps={"action": [0.0]}),
                         dataset_metadata(data_root / "source", cfg), cfg))
    actions = _actions(policy, preprocessor, postprocessor, batch)
    assert actions.shape == (cfg.batch_size, cfg.chunk_size, 7) and torch.isfinite(actions).all()
    # a checkpoint whose tensors do not fit the config: lerobot would silently keep random weights
    mismatched = _cfg(PI05, tokenizer_path=str(tiny_pi05), config=dict(PI05["config"], max_action_dim=16))
    _checkpoint(tmp_path / "other", mismatched, data_root / "source")
    with pytest.raises(PretrainedFilesError, match="not loaded"):
        build_trainer(data_root / "source", dataclasses.replace(cfg, pretrained_path=str(tmp_path / "other")))


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
