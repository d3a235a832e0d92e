"""The GPU scripts' parameter overrides are valid against params.yaml (a wrong key costs a GPU run, as
`validate.device` once did): each group of `--set` arguments in scripts/gpu/gpu_overrides.sh is read and its sections
built, with the scripts' defaults; every script, module and params file a GPU script names exists."""

from __future__ import annotations

import subprocess

import pytest

from tests.conftest import ROOT
from wc.agent.runner import AgentConfig
from wc.config import load_section, read_params
from wc.expand import ExpandConfig
from wc.sim.config import SimConfig
from wc.train.config import TrainConfig
from wc.validate.config import ValidateConfig

GROUPS = {"SIM_SETS": [("sim", SimConfig), ("agent", AgentConfig), ("validate", ValidateConfig)],
          "VAL_SETS": [("validate", ValidateConfig)],
          "TRAIN_SETS": [("train", TrainConfig)],
          "EXP_SETS": [("expand", ExpandConfig), ("validate", ValidateConfig), ("sim", SimConfig)]}


def _overrides(group: str) -> list[str]:
    words = subprocess.run(["bash", "-c", f'source scripts/gpu/gpu_overrides.sh >/dev/null; printf "%s\\n" "${{{group}[@]}}"'],
                           cwd=ROOT, capture_output=True, text=True, check=True).stdout.splitlines()
    assert words and words[0] == "--set", (group, words[:3])
    pairs = [words[i + 1] for i, w in enumerate(words) if w == "--set"]
    assert len(pairs) * 2 == len(words), f"{group}: every value follows a --set"
    return pairs


@pytest.mark.parametrize("group", sorted(GROUPS))
def test_gpu_overrides_are_valid_params(group):
    params = read_params(ROOT / "params.yaml", _overrides(group))
    for section, cls in GROUPS[group]:
        load_section(params, section, cls)
    if group == "TRAIN_SETS":
        train = load_section(params, "train", TrainConfig)
        assert train.device == "cuda" and train.select_by == "rollout" and train.input_noise_m > 0


def test_table1_params_are_valid_and_name_what_the_table1_script_unpacks():
    from wc.baselines.config import BaselinesConfig  # noqa: PLC0415
    from wc.eval.config import EvaluateConfig  # noqa: PLC0415

    params = read_params(ROOT / "params" / "gpu_table1.yaml")
    for section, cls in [("sim", SimConfig), ("agent", AgentConfig), ("validate", ValidateConfig),
                         ("train", TrainConfig), ("baselines", BaselinesConfig), ("evaluate", EvaluateConfig)]:
        load_section(params, section, cls)
    hold = (ROOT / "scripts" / "gpu" / "table1.sh").read_text()
    methods = params["evaluate"]["methods"]
    for name in params["ablations"]:  # every ablation trained is evaluated where `eval` puts it
        assert methods[name]["path"] == f"models/table1/ablations/{name}" and "no_*) dir=models/table1/ablations" in hold
    for name in params["baselines"]["names"]:
        assert methods[name]["path"] == f"models/table1/baselines/{name}"
    assert methods["worldcontact_budget"]["path"] == "models/table1/worldcontact"
    assert params["train"]["max_minutes"] == params["baselines"]["max_minutes"]  # one budget for every learned method


def test_the_extra_overrides_the_gpu_scripts_pass_name_existing_params():
    """`EXTRA_*_SETS="--set key=value ..."` in scripts/gpu/*.sh: every key is one params.yaml has (an unknown key
    fails the stage on the GPU machine, after the data were simulated)."""
    import re  # noqa: PLC0415
    import shlex  # noqa: PLC0415

    base = read_params(ROOT / "params.yaml")
    found = 0
    for script in sorted((ROOT / "scripts" / "gpu").glob("*.sh")):
        for extra in re.findall(r'EXTRA_[A-Z]+_SETS="([^"]*)"', script.read_text()):
            words = shlex.split(extra)
            assert words[::2] == ["--set"] * (len(words) // 2) and len(words) % 2 == 0, (script.name, extra)
            for pair in words[1::2]:
                node = base
                for part in pair.split("=", 1)[0].split("."):
                    assert isinstance(node, dict) and part in node, f"{script.name}: unknown param in --set {pair}"
                    node = node[part]
                found += 1
    assert found >= 5


def test_what_the_gpu_scripts_name_exists():
    """Every `scripts/gpu/X` a GPU script runs or sources, every `python -m M` module and every `params/F.yaml` it
    passes exists (a renamed script or module fails on the GPU machine, after the data were simulated)."""
    import importlib.util  # noqa: PLC0415
    import re  # noqa: PLC0415

    named = 0
    for script in sorted((ROOT / "scripts" / "gpu").glob("*.sh")):
        text = "\n".join(line.split("#", 1)[0] for line in script.read_text().splitlines())  # commands, not comments
        for path in re.findall(r"(scripts/gpu/[\w./-]+|params/[\w.]+\.yaml)", text):
            assert (ROOT / path).exists(), f"{script.name}: {path} does not exist"
            named += 1
        for module in re.findall(r"python3? -m ([\w.]+)", text):
            assert importlib.util.find_spec(module) is not None, f"{script.name}: no module {module}"
            named += 1
    assert named >= 30
