"""The stages' default paths (wc/paths.py, the one place the command lines and work functions take them from)
against dvc.yaml: every data / model / report path a `python -m stages.<name>` stage reads or writes, by default
or as its cmd sets it, is among that DVC stage's deps, outs, metrics or plots, so the two cannot drift.
Fast: reads YAML only."""

from __future__ import annotations

import shlex
from typing import Any

import pytest
import yaml

from tests.conftest import ROOT
from wc.paths import RENDER_PAIRS, STAGES
from wc.stage_cli import flag

TRACKED = ("data/", "models/", "reports/")  # what DVC versions; e.g. the folder `reports` itself is not a file
OPTIONS = {"render": {"--inputs", "--outs"}}  # flags a stage's cmd may pass besides --params, --set and its paths


def _dvc_stages() -> dict[str, dict[str, Any]]:
    """dvc.yaml's stages that run `python -m stages.<module>`, each with its `module` (a foreach stage: its `do`)."""
    stages = {}
    for name, stage in yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"].items():
        body = stage.get("do", stage)
        words = shlex.split(body["cmd"])
        if "-m" in words and words[words.index("-m") + 1].startswith("stages."):
            stages[name] = {**body, "module": words[words.index("-m") + 1].removeprefix("stages."), "words": words}
    return stages


def _declared(stage: dict[str, Any]) -> set[str]:
    """The paths of a DVC stage's deps, outs, metrics and plots (an entry may be `path: {options}`)."""
    return {next(iter(e)) if isinstance(e, dict) else e
            for key in ("deps", "outs", "metrics", "plots") for e in stage.get(key, [])}


def _flag_values(words: list[str], name: str) -> list[str]:
    """The values after `name` in a command line, up to the next flag ([] when it is not given)."""
    if name not in words:
        return []
    rest = words[words.index(name) + 1:]
    return rest[:next((i for i, w in enumerate(rest) if w.startswith("--")), len(rest))]


DVC_STAGES = _dvc_stages()


def test_every_stage_declares_its_paths() -> None:
    assert {s["module"] for s in DVC_STAGES.values()} == set(STAGES)


@pytest.mark.parametrize("name", sorted(DVC_STAGES))
def test_stage_paths_match_dvc_yaml(name: str) -> None:
    stage = DVC_STAGES[name]
    declared, words = _declared(stage), stage["words"]
    paths = STAGES[stage["module"]]
    known = {"--params", "--set", *map(flag, paths), *OPTIONS.get(stage["module"], ())}
    assert {w for w in words if w.startswith("--")} <= known, f"{name}: cmd passes a flag the stage does not have"
    for key, default in paths.items():
        given = _flag_values(words, flag(key))
        path = given[0] if given else default
        if path.startswith(TRACKED):
            assert path in declared, f"{name}: {flag(key)} {path} is not among dvc.yaml's deps/outs/metrics/plots"


def test_render_pairs_match_dvc_yaml() -> None:
    stage = DVC_STAGES["render"]
    declared = _declared(stage)
    inputs, outs = _flag_values(stage["words"], "--inputs"), _flag_values(stage["words"], "--outs")
    assert list(zip(inputs, outs)) == list(RENDER_PAIRS)  # the cmd renders what the stage renders by default
    assert set(inputs) <= {d for d in stage["deps"] if isinstance(d, str)}
    assert set(outs) <= declared
