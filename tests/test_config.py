"""Params loading: every malformed params file fails with a message naming the key and the file."""

from pathlib import Path

import pytest
import yaml

from wc.config import ParamsError, load_section, params_hash, read_params
from wc.scene.config import SceneConfig
from wc.sim.config import SimConfig
from wc.tasks.base import get_task, task_names

ROOT = Path(__file__).resolve().parents[1]


def _write(tmp_path: Path, data: dict) -> Path:
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize("file", ["params.yaml", "params/gpu.yaml"])
def test_shipped_params_load(file):
    params = read_params(ROOT / file)
    assert load_section(params, "scene", SceneConfig).bag.target_vertices > 0
    assert load_section(params, "sim", SimConfig).frame_dt_s == pytest.approx(0.04)
    for name in params["agent"]["tasks"]:
        get_task(name, params)


@pytest.mark.parametrize("file", ["params.yaml", "params/gpu.yaml"])
def test_every_stage_section_of_the_shipped_params_validates(file):
    """Each file carries every stage's section, so any stage runs with `--params FILE`."""
    from wc.agent.runner import AgentConfig
    from wc.baselines.config import BaselinesConfig
    from wc.eval.config import EvaluateConfig
    from wc.expand.config import ExpandConfig
    from wc.model.config import ModelConfig
    from wc.policy.dataset_config import DatasetConfig
    from wc.policy.policy_config import PolicyConfig
    from wc.policy_eval.config import PolicyEvalConfig
    from wc.render.config import RenderConfig
    from wc.train.config import TrainConfig
    from wc.validate.config import ValidateConfig
    params = read_params(ROOT / file)
    for name, config in {"agent": AgentConfig, "validate": ValidateConfig, "model": ModelConfig,
                         "train": TrainConfig, "baselines": BaselinesConfig, "evaluate": EvaluateConfig,
                         "expand": ExpandConfig, "render": RenderConfig, "dataset": DatasetConfig,
                         "policy": PolicyConfig, "policy_eval": PolicyEvalConfig}.items():
        load_section(params, name, config)  # raises ParamsError naming a missing, unknown or invalid key


def test_unknown_key_is_named(tmp_path):
    data = read_params(ROOT / "params.yaml")
    data["sim"]["iteratons"] = 3
    with pytest.raises(ParamsError, match=r"unknown key sim\.iteratons"):
        load_section(read_params(_write(tmp_path, data)), "sim", SimConfig)


def test_missing_key_is_named(tmp_path):
    data = read_params(ROOT / "params.yaml")
    del data["scene"]["bag"]["height_m"]
    path = _write(tmp_path, data)
    with pytest.raises(ParamsError, match=r"missing key scene\.bag\.height_m") as err:
        load_section(read_params(path), "scene", SceneConfig)
    assert str(path) in str(err.value)


@pytest.mark.parametrize("value", [0, -5])
def test_non_positive_resolution_rejected(tmp_path, value):
    params = read_params(ROOT / "params.yaml", [f"scene.bag.target_vertices={value}"])
    with pytest.raises(ParamsError, match="target_vertices must be positive"):
        load_section(params, "scene", SceneConfig)


def test_wrong_type_rejected():
    params = read_params(ROOT / "params.yaml", ["sim.iterations=ten"])
    with pytest.raises(ParamsError, match=r"sim\.iterations must be an integer"):
        load_section(params, "sim", SimConfig)


def test_override_of_unknown_key_rejected():
    with pytest.raises(ParamsError, match="unknown key"):
        read_params(ROOT / "params.yaml", ["sim.nope=1"])


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(ParamsError, match="not found"):
        read_params(tmp_path / "absent.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("sim: [unclosed")
    with pytest.raises(ParamsError, match="not valid YAML"):
        read_params(bad)


def test_unknown_task_lists_known_ones():
    params = read_params(ROOT / "params.yaml")
    with pytest.raises(ValueError, match="unknown task 'fold_shirt'.*lift_handle"):
        get_task("fold_shirt", params)
    assert "lift_handle" in task_names()


def test_params_hash_tracks_content():
    a = read_params(ROOT / "params.yaml")
    b = read_params(ROOT / "params.yaml", ["sim.iterations=3"])
    assert params_hash(a, ["sim"]) != params_hash(b, ["sim"])
    assert params_hash(a, ["scene"]) == params_hash(b, ["scene"])


@pytest.mark.parametrize("file", ["params.yaml", "params/gpu.yaml"])
def test_every_ablation_changes_one_valid_model_key(file):
    """dvc.yaml's train_ablation stage runs `stages.train --set <value>` for each `ablations` entry: each value
    must be one override of a model key, giving a model config that validates and differs from the full model's."""
    from wc.model.config import ModelConfig
    params = read_params(ROOT / file)
    assert params["ablations"], "no ablation to train"
    full = load_section(params, "model", ModelConfig)
    for name, override in params["ablations"].items():
        key, _, _ = override.partition("=")
        assert key.startswith("model.") and key.count(".") == 1, (name, override)
        ablated = load_section(read_params(ROOT / file, [override]), "model", ModelConfig)
        assert ablated != full, name


def test_gpu_params_train_both_paper_ablations():
    assert set(read_params(ROOT / "params/gpu.yaml")["ablations"]) == {"no_contact_tokenizer",
                                                                       "no_hierarchical_compression"}


@pytest.mark.parametrize("file", ["params.yaml", "params/gpu.yaml"])
def test_demonstrations_hold_as_long_as_policy_success_asks(file):
    """The policy task's demonstrations (simulated and generated with its task params) hold the bag at least as
    long as policy_eval's success hold, so the policy is trained on what it is judged by."""
    params = read_params(ROOT / file)
    task = params["policy_eval"]["task"]
    assert params["dataset"]["task"] == params["expand"]["task"] == task
    assert params["tasks"][task]["hold_s"] >= params["policy_eval"]["hold_s"] >= 2.0


def test_sim_rejects_a_negative_self_contact_filter():
    params = read_params(ROOT / "params.yaml", ["sim.self_contact_filter_rings=-1"])
    with pytest.raises(ParamsError, match="self_contact_filter_rings"):
        load_section(params, "sim", SimConfig)


def test_an_override_file_extends_its_base(tmp_path):
    """`extends` loads the base first; mappings merge key by key, `!replace` replaces one whole, lists replace."""
    (tmp_path / "base.yaml").write_text(yaml.safe_dump(
        {"sim": {"dt_s": 0.04, "worlds": 1, "bag": {"ke": 1.0, "kd": 2.0}}, "cases": {"a": {"x": 1}, "b": {"y": 2}},
         "tasks": [1, 2]}))
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "gpu.yaml").write_text("extends: ../base.yaml\nsim: {worlds: 8, bag: {kd: 3.0}}\n"
                                               "cases: !replace {c: {z: 3}}\ntasks: [3]\n")
    params = read_params(tmp_path / "sub" / "gpu.yaml", ["sim.dt_s=0.02"])
    assert params["sim"] == {"dt_s": 0.02, "worlds": 8, "bag": {"ke": 1.0, "kd": 3.0}}
    assert params["cases"] == {"c": {"z": 3}} and params["tasks"] == [3]
    (tmp_path / "loop.yaml").write_text("extends: loop.yaml\n")
    with pytest.raises(ParamsError, match="extend each other in a cycle"):
        read_params(tmp_path / "loop.yaml")
    (tmp_path / "orphan.yaml").write_text("extends: nowhere.yaml\n")
    with pytest.raises(ParamsError, match=r"params file not found: .*nowhere.yaml \(extended by"):
        read_params(tmp_path / "orphan.yaml")


def test_an_override_file_extends_several_bases_in_order(tmp_path):
    """`extends: [a, b]`: b merged on top of a, then the file itself on top; each base may extend its own."""
    (tmp_path / "a.yaml").write_text("sim: {worlds: 1, dt_s: 0.04}\npolicy: {steps: 80, lr: 1.0}\n")
    (tmp_path / "b.yaml").write_text("extends: a.yaml\npolicy: {steps: 3500}\n")
    (tmp_path / "recipe.yaml").write_text("policy: {lr: 2.0}\n")
    (tmp_path / "run.yaml").write_text("extends: [b.yaml, recipe.yaml]\nsim: {worlds: 8}\n")
    params = read_params(tmp_path / "run.yaml")
    assert params["sim"] == {"worlds": 8, "dt_s": 0.04} and params["policy"] == {"steps": 3500, "lr": 2.0}
    (tmp_path / "bad.yaml").write_text("extends: [a.yaml, 3]\n")
    with pytest.raises(ParamsError, match="extends must name a params file or a list of them"):
        read_params(tmp_path / "bad.yaml")


def test_the_gpu_params_list_only_what_differs_from_the_defaults():
    """params/gpu.yaml is an override of params.yaml: every value it sets differs from the default it overrides."""
    from wc.config import _ParamsLoader

    override = yaml.load((ROOT / "params/gpu.yaml").read_text(), Loader=_ParamsLoader)
    assert override.pop("extends") == "../params.yaml"
    base = read_params(ROOT / "params.yaml")

    def same(node: dict, at: dict | None, path: str) -> list[str]:
        found = []
        for key, value in node.items():
            there = at.get(key) if isinstance(at, dict) else None
            if isinstance(value, dict) and type(value) is dict and isinstance(there, dict):
                found += same(value, there, f"{path}{key}.")
            elif value == there:
                found.append(f"{path}{key}")
        return found

    assert same(override, base, "") == []


def test_fine_tune_scales_every_learning_rate_only_from_a_checkpoint():
    from dataclasses import replace

    from wc.train.config import TrainConfig
    cfg = load_section(read_params(Path(__file__).resolve().parents[1] / "params.yaml"), "train", TrainConfig)
    scratch = replace(cfg, init_from="", fine_tune_lr_scale=0.1)
    assert scratch.run_config() == scratch
    tuned = replace(cfg, init_from="models/some.safetensors", fine_tune_lr_scale=0.1).run_config()
    for before, after in ((cfg.base, tuned.base), (cfg.projection, tuned.projection)):
        assert after.steps == before.steps and after.warmup_steps == before.warmup_steps
        assert (after.peak_lr, after.start_lr, after.final_lr) == pytest.approx(
            (0.1 * before.peak_lr, 0.1 * before.start_lr, 0.1 * before.final_lr))
    with pytest.raises(ValueError, match="fine_tune_lr_scale"):
        replace(cfg, fine_tune_lr_scale=0.0).validate()
