"""One rule for params `device` values (wc/devices.py), shared by every section that has one."""

from __future__ import annotations

import copy

import pytest
import torch

from tests.conftest import default_params
from wc.config import ParamsError, load_section
from wc.devices import check_device_name, resolve_device, resolve_warp_device
from wc.eval.config import EvaluateConfig
from wc.expand import ExpandConfig
from wc.policy_eval.config import PolicyEvalConfig
from wc.render.config import RenderConfig
from wc.validate.config import ValidateConfig


@pytest.mark.parametrize("name", ["cpu", "cuda", "cuda:0", "cuda:12", "auto"])
def test_valid_names(name):
    check_device_name(name, "x.device")


@pytest.mark.parametrize("name", ["gpu", "cuda:", "cuda:a", "CPU", "", "cuda0", 0, None])
def test_invalid_names_are_named_with_their_key(name):
    with pytest.raises(ValueError, match="x.device must be cpu, cuda, cuda:N or auto"):
        check_device_name(name, "x.device")


def test_auto_can_be_refused():
    with pytest.raises(ValueError, match="policy.device must be cpu, cuda, cuda:N, got 'auto'"):
        check_device_name("auto", "policy.device", allow_auto=False)


def test_resolvers_apply_the_rule_and_resolve_auto():
    with pytest.raises(ValueError, match="evaluate.device must be"):
        resolve_device("gpu", "evaluate.device")
    with pytest.raises(ValueError, match="sim.device must be"):
        resolve_warp_device("cuda:x", "sim.device")
    assert resolve_device("auto", "k").type == ("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_warp_device("cpu", "k") == "cpu"


@pytest.mark.parametrize("section, cls", [("evaluate", EvaluateConfig), ("expand", ExpandConfig),
                                          ("policy_eval", PolicyEvalConfig), ("render", RenderConfig),
                                          ("validate", ValidateConfig)])
def test_every_section_uses_the_rule(section, cls):
    params = copy.deepcopy(default_params())
    params[section]["device"] = "cuda:x"
    with pytest.raises(ParamsError, match="must be cpu, cuda, cuda:N or auto"):
        load_section(params, section, cls)
