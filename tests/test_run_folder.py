"""Run folders (wc/run_folder.py): a configuration's params resolved, the root dvc.yaml's stages it needs rewritten to
run in the folder, and the committed GPU run's config valid before it costs GPU time. Fast: YAML only."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml

from tests.conftest import ROOT
from wc.config import ParamsError, load_section, read_params
from wc.run_folder import needed_stages, record_files, resolve_config, run_pipeline, write_run_folder
from wc.smoke import smoke_label

ROOT_DVC = yaml.safe_load((ROOT / "dvc.yaml").read_text())
PARAMS = read_params(ROOT / "params.yaml")


def test_a_run_needs_its_targets_and_every_stage_upstream():
    stages = ROOT_DVC["stages"]
    assert needed_stages(stages, ["train"], PARAMS) == ["simulate", "validate", "train"]
    evaluate = needed_stages(stages, ["evaluate"], PARAMS)  # models/ablations: the foreach stage's instances
    assert evaluate == ["simulate", "validate", "train", "train_ablation", "train_baselines", "evaluate"]
    assert needed_stages(stages, ["train"], PARAMS, inputs=["data/source/trajectories.zarr"]) == ["train"]
    with pytest.raises(ParamsError, match="no stage 'trian' in dvc.yaml"):
        needed_stages(stages, ["trian"], PARAMS)


def test_a_run_folder_stage_reads_code_from_the_repository_and_writes_into_the_folder():
    run = run_pipeline(ROOT_DVC, ["train", "train_ablation"], PARAMS, "../..")
    train, root_train = run["stages"]["train"], ROOT_DVC["stages"]["train"]
    assert train["cmd"] == "../../" + root_train["cmd"] and " --params params.yaml" in train["cmd"]
    assert "../../wc/model" in train["deps"] and "../../models/pretrained/worldcontact-lift-handle" in train["deps"]
    assert "data/source/trajectories.zarr" in train["deps"]  # made by this run's validate stage
    assert train["outs"] == root_train["outs"] and train["params"] == root_train["params"]
    ablation = run["stages"]["train_ablation"]
    assert ablation["foreach"] == "${ablations}" and ablation["do"]["cmd"].startswith("../../.venv/bin/python ")
    assert "data/source/trajectories.zarr" in ablation["do"]["deps"] and "../../wc/train" in ablation["do"]["deps"]
    drawn = {next(iter(p)) for p in run["plots"]}
    assert drawn == {"reports/train_loss.csv", "reports/simulate_lift.csv"}  # not evaluate's: it does not run here


def test_the_gpu_policy_run_is_valid_before_it_costs_gpu_time():
    """runs/gpu_policy/config.yaml: every section its stages read builds, on the GPU, with the ACT recipe; the shipped
    model it fine-tunes is found from the run folder."""
    from wc.agent.runner import AgentConfig  # noqa: PLC0415
    from wc.expand import ExpandConfig  # noqa: PLC0415
    from wc.policy.dataset_config import DatasetConfig  # noqa: PLC0415
    from wc.policy.policy_config import PolicyConfig  # noqa: PLC0415
    from wc.policy_eval.config import PolicyEvalConfig  # noqa: PLC0415
    from wc.render.config import RenderConfig  # noqa: PLC0415
    from wc.sim.config import SimConfig  # noqa: PLC0415
    from wc.train.config import TrainConfig  # noqa: PLC0415
    from wc.validate.config import ValidateConfig  # noqa: PLC0415

    folder = ROOT / "runs" / "gpu_policy"
    params, targets, inputs = resolve_config(folder / "config.yaml")
    sections = {"sim": SimConfig, "agent": AgentConfig, "validate": ValidateConfig, "train": TrainConfig,
                "expand": ExpandConfig, "render": RenderConfig, "dataset": DatasetConfig, "policy": PolicyConfig,
                "policy_eval": PolicyEvalConfig}
    built = {name: load_section(params, name, cls) for name, cls in sections.items()}
    assert {name: cfg.device for name, cfg in built.items() if hasattr(cfg, "device")} == {
        "sim": "cuda", "validate": "cuda", "train": "cuda", "expand": "cuda", "render": "cuda", "policy": "cuda",
        "policy_eval": "cuda"}
    assert built["policy"].steps == 3500 and tuple(built["policy"].datasets) == ("source", "expanded")
    assert built["policy_eval"].trials == 50 and built["expand"].target_trajectories == 150
    assert (folder / built["train"].init_from / "model.safetensors").is_file()
    stages = needed_stages(ROOT_DVC["stages"], targets, params)
    assert inputs == [] and stages == [
        "simulate", "validate", "train", "render", "dataset", "expand", "finetune", "policy_eval"]
    assert not [s for s in stages if smoke_label(params, s)], "a GPU result labelled a smoke run"


def test_write_run_folder_resolves_the_params_and_keeps_the_root_untouched(tmp_path):
    for name in ("dvc.yaml", "params.yaml"):
        shutil.copy(ROOT / name, tmp_path / name)
    folder = tmp_path / "runs" / "tiny"
    folder.mkdir(parents=True)
    (folder / "config.yaml").write_text("extends: ../../params.yaml\npipeline: {targets: [train, train_ablation]}\n"
                                        "train: {base: {steps: 3}}\n")
    written = write_run_folder(folder, tmp_path)
    assert written["stages"] == ["simulate", "validate", "train", "train_ablation"]
    params = yaml.safe_load((folder / "params.yaml").read_text())
    expected = read_params(ROOT / "params.yaml", ["train.base.steps=3"])
    assert params == {k: v for k, v in expected.items() if k != "_source"}  # every value; no `pipeline` section
    assert yaml.safe_load((folder / "dvc.yaml").read_text())["stages"]["train"]["cmd"].startswith("../../.venv/")
    assert (tmp_path / "dvc.yaml").read_text() == (ROOT / "dvc.yaml").read_text()
    frozen = {n: s["frozen"] for n, s in yaml.safe_load((folder / "dvc.yaml").read_text())["stages"].items()}
    assert set(frozen.values()) == {True}  # the root `dvc repro` leaves the run alone
    write_run_folder(folder, tmp_path, frozen=False)  # the driver, to run it
    assert not any(s["frozen"] for s in yaml.safe_load((folder / "dvc.yaml").read_text())["stages"].values())
    write_run_folder(folder, tmp_path)
    (folder / "reports" / "ablations").mkdir(parents=True)
    for report in ("train.json", "ablations/no_contact_tokenizer.json"):  # cache-free outputs: part of the record
        (folder / "reports" / report).write_text("{}")
    (folder / "data").mkdir()
    assert record_files(folder) == [f"{folder.as_posix()}/{n}" for n in (
        "config.yaml", "params.yaml", "dvc.yaml", ".gitignore", "reports/train.json",
        "reports/ablations/no_contact_tokenizer.json")]
    ignored = (folder / ".gitignore").read_text().splitlines()[1:]  # what DVC caches; git keeps the rest
    assert "/models/worldcontact" in ignored and "/data/source/trajectories.zarr" in ignored
    assert not any(line.startswith("/reports/") for line in ignored), ignored


@pytest.mark.parametrize("pipeline, problem", [
    ("{}", "pipeline.targets must list"), ("{targets: [train], input: [x]}", "unknown key pipeline.input"),
    ("{targets: [train], inputs: data}", "pipeline.inputs must list")])
def test_a_bad_pipeline_section_is_named(tmp_path, pipeline, problem):
    shutil.copy(ROOT / "params.yaml", tmp_path / "params.yaml")
    (tmp_path / "config.yaml").write_text(f"extends: params.yaml\npipeline: {pipeline}\n")
    with pytest.raises(ParamsError, match=problem):
        resolve_config(tmp_path / "config.yaml")


def test_a_run_folder_outside_the_repository_is_refused(tmp_path):
    (tmp_path / "outside").mkdir()
    (tmp_path / "outside" / "config.yaml").write_text("pipeline: {targets: [train]}\n")
    (tmp_path / "repo").mkdir()
    with pytest.raises(ParamsError, match="is not inside the repository"):
        write_run_folder(tmp_path / "outside", tmp_path / "repo")
    with pytest.raises(FileNotFoundError, match="no .*config.yaml"):
        write_run_folder(tmp_path / "repo", tmp_path)


def test_the_generated_files_are_the_runs_record_not_hand_edits():
    """A run folder in the repository holds its config; the files the driver writes say where they come from."""
    for folder in sorted((ROOT / "runs").iterdir()):
        assert (folder / "config.yaml").is_file(), folder
        for name in ("params.yaml", "dvc.yaml"):
            if (folder / name).is_file():
                assert (folder / name).read_text().startswith("# Written by `python -m wc.run_folder"), folder / name
        if (folder / "dvc.yaml").is_file():  # committed frozen: the root `dvc repro` (every dvc.yaml) skips it
            stages = yaml.safe_load((folder / "dvc.yaml").read_text())["stages"].values()
            assert all(stage.get("frozen") is True for stage in stages), folder
