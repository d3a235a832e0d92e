"""train.init_from: fine-tuning starts from a pretrained checkpoint (a path or a hub file), whose architecture the
params must match, and a missing or mismatched checkpoint fails naming the problem."""

from __future__ import annotations

import copy
import shutil
from pathlib import Path
from typing import Any

from huggingface_hub import constants as hub_constants
import pytest
import torch
from safetensors.torch import load_file

from wc.train.train_stage import run
from tests.conftest import default_params
from tests.synthetic_store import write_synthetic_store
from wc.model_ref import resolve_weights

# every test uses `pretrained`, a stage run from scratch
pytestmark = pytest.mark.slow
EPISODES = [("fall", "train"), ("carry", "train"), ("fall", "val")]
STEPS = {"base": {"steps": 2, "peak_lr": 1e-3, "start_lr": 1e-4, "final_lr": 1e-4, "warmup_steps": 1},
         "projection": {"steps": 0, "peak_lr": 0.0, "start_lr": 0.0, "final_lr": 0.0, "warmup_steps": 0},
         "eval_every_steps": 1, "val_windows": 2, "rollout_frames": 4}
FROZEN = {"steps": 1, "peak_lr": 0.0, "start_lr": 0.0, "final_lr": 0.0, "warmup_steps": 0}  # AdamW at lr 0: no change


@pytest.fixture(scope="module")
def pretrained(tmp_path_factory) -> tuple[dict[str, Any], Path, Path]:
    """Params, a store and a model trained from scratch on it (the 'pretrained' checkpoint)."""
    d = tmp_path_factory.mktemp("pretrained")
    params = default_params(STEPS)
    store = write_synthetic_store(d / "s.zarr", params, EPISODES, frames=8)
    run(params, store, d / "model", d / "train.json", d / "train_loss.csv")
    return params, store, d / "model"


def _fine_tune(params: dict[str, Any], store: Path, init_from: str, out: Path, **model: Any) -> dict[str, Any]:
    tuned = copy.deepcopy(params)
    tuned["train"].update(init_from=init_from, base=dict(FROZEN))
    tuned["model"].update(model)
    return run(tuned, store, out / "model", out / "train.json", out / "train_loss.csv")


def _weights(path: Path) -> dict[str, torch.Tensor]:
    return load_file(str(path / "model.safetensors"))


def test_fine_tuning_starts_from_the_checkpoint(pretrained, tmp_path):
    params, store, model_dir = pretrained
    report = _fine_tune(params, store, str(model_dir), tmp_path)
    assert report["init_from"] == str(model_dir)
    ours, theirs = _weights(tmp_path / "model"), _weights(model_dir)
    assert ours.keys() == theirs.keys() and all(torch.equal(ours[k], theirs[k]) for k in ours)
    scratch = copy.deepcopy(params)
    scratch["train"]["base"] = dict(FROZEN)
    fresh = run(scratch, store, tmp_path / "fresh", tmp_path / "fresh.json", tmp_path / "fresh.csv")
    assert fresh["init_from"] == "" and fresh["best_val_loss"] != report["best_val_loss"]


def test_a_hub_file_resolves_through_the_cache(pretrained, tmp_path, monkeypatch):
    """hf://owner/repo/file resolves offline from a Hugging Face cache holding the file and its .json."""
    _, _, model_dir = pretrained
    snapshot = tmp_path / "hub" / "models--worldcontact--pretrained" / "snapshots" / ("a" * 40)
    (snapshot / "bag").mkdir(parents=True)
    for suffix in (".safetensors", ".json"):
        shutil.copyfile(model_dir / f"model{suffix}", snapshot / "bag" / f"model{suffix}")
    (snapshot.parents[1] / "refs").mkdir()
    (snapshot.parents[1] / "refs" / "main").write_text("a" * 40)
    monkeypatch.setattr(hub_constants, "HF_HUB_CACHE", str(tmp_path / "hub"))
    monkeypatch.setattr(hub_constants, "HF_HUB_OFFLINE", True)
    assert resolve_weights("hf://worldcontact/pretrained/bag/model.safetensors") == snapshot / "bag" / "model.safetensors"
    assert resolve_weights("hf://worldcontact/pretrained/bag") == snapshot / "bag" / "model.safetensors"  # a folder
    with pytest.raises(FileNotFoundError, match="not available from the hub or its cache"):
        resolve_weights("hf://worldcontact/pretrained/other/model.safetensors")
    with pytest.raises(ValueError, match="a hub model is hf://owner/repo"):
        resolve_weights("hf://worldcontact/model.safetensors")


def test_a_missing_or_mismatched_checkpoint_fails_naming_it(pretrained, tmp_path):
    params, store, model_dir = pretrained
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        _fine_tune(params, store, str(tmp_path / "nowhere"), tmp_path)
    with pytest.raises(ValueError, match=r"kernel_size: params 3 vs checkpoint 4"):
        _fine_tune(params, store, str(model_dir), tmp_path, kernel_size=3)
    assert not (tmp_path / "model").exists()


def test_the_shipped_pretrained_model_fine_tunes_under_the_default_params(pretrained, tmp_path):
    """models/pretrained/worldcontact-lift-handle matches params.yaml's model section, so the CPU default's train
    stage can start from it (train.init_from), and its weights arrive unchanged."""
    params, store, _ = pretrained
    shipped = Path(__file__).resolve().parents[1] / "models/pretrained/worldcontact-lift-handle/model.safetensors"
    report = _fine_tune(params, store, str(shipped), tmp_path)
    assert report["init_from"] == str(shipped)
    ours, theirs = _weights(tmp_path / "model"), load_file(str(shipped))
    assert ours.keys() == theirs.keys() and all(torch.equal(ours[k], theirs[k]) for k in ours)
