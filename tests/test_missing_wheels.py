"""scripts/gpu/missing_wheels.py: the pip specs an offline machine lacks, read from this checkout's environment."""

from __future__ import annotations

import importlib.util
from importlib import metadata

from tests.conftest import ROOT

_spec = importlib.util.spec_from_file_location("missing_wheels", ROOT / "scripts" / "gpu" / "missing_wheels.py")
missing_wheels = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(missing_wheels)


def test_the_closure_follows_dependencies_and_extras_at_the_installed_versions():
    dvc = missing_wheels.closure(["dvc"])
    assert dvc["dvc"] == metadata.version("dvc") and dvc["dvc-data"] == metadata.version("dvc-data")
    assert {"scmrepo", "dulwich", "pygit2", "funcy"} <= set(dvc) and "torch" not in dvc
    plain, extra = missing_wheels.closure(["lerobot"]), missing_wheels.closure(["lerobot[dataset]"])
    assert "datasets" in extra and "av" in extra and "datasets" not in plain  # an extra's requirements only with it


def test_only_what_the_machine_lacks_is_listed(tmp_path, capsys):
    (tmp_path / "have.txt").write_text("# pip list --format=freeze\nfuncy==2.0\nDulwich==1.0\npygit2\n")
    missing_wheels.main(["dvc", "--have", str(tmp_path / "have.txt")])
    listed = capsys.readouterr().out.split()
    assert f"dvc=={metadata.version('dvc')}" in listed and f"scmrepo=={metadata.version('scmrepo')}" in listed
    assert not [s for s in listed if s.split("==")[0] in ("funcy", "dulwich", "pygit2")]
    missing_wheels.main(["--have", str(tmp_path / "have.txt"), "--skip", "ray"])  # pyproject.toml's requirements
    listed = capsys.readouterr().out.split()
    assert f"warp-lang=={metadata.version('warp-lang')}" in listed and f"lerobot=={metadata.version('lerobot')}" in listed
    assert not [s for s in listed if s.startswith("ray==")]
