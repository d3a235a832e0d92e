"""One resolver for every model path (wc/model_ref.py): a model folder, a weights file or a Hugging Face Hub model
hf://owner/repo[/folder] load the same weights, in load_model, evaluate and expand; reports record the weights' hash."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

from huggingface_hub import constants as hub_constants
import pytest
import torch

from tests.conftest import ROOT, load_params
from wc.config import load_section
from wc.eval.config import MethodSpec
from wc.eval.predictors import WorldContactPredictor, load_predictor
from wc.model_ref import model_record, resolve_model_dir, resolve_weights
from wc.train.checkpoint import load_model
from wc.train.config import TrainConfig

SHIPPED = ROOT / "models" / "pretrained" / "worldcontact-lift-handle"


@pytest.fixture()
def hub(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """An offline Hugging Face cache holding the shipped model at the root of repo worldcontact/lift-handle and
    under folder stage3/: the snapshot folder."""
    snapshot = tmp_path / "hub" / "models--worldcontact--lift-handle" / "snapshots" / ("b" * 40)
    for folder in (snapshot, snapshot / "stage3"):
        folder.mkdir(parents=True, exist_ok=True)
        for name in ("model.safetensors", "model.json"):
            shutil.copyfile(SHIPPED / name, folder / name)
    (snapshot.parents[1] / "refs").mkdir()
    (snapshot.parents[1] / "refs" / "main").write_text("b" * 40)
    monkeypatch.setattr(hub_constants, "HF_HUB_CACHE", str(tmp_path / "hub"))
    monkeypatch.setattr(hub_constants, "HF_HUB_OFFLINE", True)
    return snapshot


def test_the_model_cards_load_line_works() -> None:
    """The card says `load_model("models/pretrained/worldcontact-lift-handle")`: the folder loads as its file does."""
    model, config = load_model(SHIPPED)
    same, _ = load_model(SHIPPED / "model.safetensors")
    assert config["step"] == json.loads((SHIPPED / "model.json").read_text())["step"] and not model.training
    assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), same.state_dict().values()))


def test_hub_folders_and_files_resolve_from_the_cache(hub: Path) -> None:
    assert resolve_weights("hf://worldcontact/lift-handle") == hub / "model.safetensors"
    assert resolve_model_dir("hf://worldcontact/lift-handle/stage3") == hub / "stage3"
    assert resolve_weights("hf://worldcontact/lift-handle/stage3/model.safetensors@main") == hub / "stage3" / "model.safetensors"
    with pytest.raises(FileNotFoundError, match="expand --model 'hf://worldcontact/lift-handle/stage2': not available"):
        resolve_model_dir("hf://worldcontact/lift-handle/stage2", "expand --model")
    for bad in ("hf://worldcontact", "hf://worldcontact/model.safetensors", "hf://a//b"):
        with pytest.raises(ValueError, match="a hub model is hf://owner/repo"):
            resolve_weights(bad)
    with pytest.raises(FileNotFoundError, match="checkpoint not found: nowhere .a model folder holding model.safetensors"):
        resolve_weights("nowhere")


def test_evaluate_loads_a_hub_model_and_skips_a_missing_folder(hub: Path) -> None:
    train_cfg = load_section(load_params(), "train", TrainConfig)
    predictor = load_predictor(MethodSpec(kind="worldcontact", path="hf://worldcontact/lift-handle/stage3"), train_cfg,
                               torch.device("cpu"))
    local = WorldContactPredictor.from_dir(SHIPPED, train_cfg, torch.device("cpu"))
    assert all(torch.equal(a, b) for a, b in zip(predictor.model.state_dict().values(), local.model.state_dict().values()))
    with pytest.raises(FileNotFoundError, match="checkpoint directory models/none not found"):
        load_predictor(MethodSpec(kind="worldcontact", path="models/none"), train_cfg, torch.device("cpu"))


def test_a_model_record_names_the_weights_by_their_hash(hub: Path) -> None:
    record = model_record(SHIPPED)
    meta = json.loads((SHIPPED / "model.json").read_text())
    assert record == {"path": str(SHIPPED), "sha256": hashlib.sha256((SHIPPED / "model.safetensors").read_bytes()).hexdigest(),
                      "params_hash": meta["params_hash"], "step": meta["step"], "stage": meta["stage"]}
    assert model_record("hf://worldcontact/lift-handle")["sha256"] == record["sha256"]
    assert model_record("hf://worldcontact/lift-handle")["path"] == "hf://worldcontact/lift-handle"
