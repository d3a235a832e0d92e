"""Every result versioned, for real: the project's own pipeline (a run folder of two cheap stages, train and
train_baselines, on a small synthetic store with tiny params) run by the GPU driver (scripts/gpu/run_pipeline.sh) on
the CPU, resumed stage by stage, pushed to the default DVC remote (pointed at a temporary folder), cloned afresh with
git, pulled, and found unchanged byte for byte; then carried to another checkout as pieces (pack / unpack) with no
remote at all, where the driver runs nothing again."""

from __future__ import annotations

import filecmp
import os
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from tests.conftest import ROOT, load_params
from tests.test_baselines import TINY as TINY_BASELINES
from tests.test_train import EPISODES

# Two training steps of a one-level model and one baseline: what is versioned matters here, not the models.
TINY = {"train": {"base": {"steps": 2, "peak_lr": 1e-3, "start_lr": 1e-4, "final_lr": 1e-4, "warmup_steps": 1},
                  "projection": {"steps": 0, "peak_lr": 1e-4, "start_lr": 1e-5, "final_lr": 1e-5, "warmup_steps": 0},
                  "eval_every_steps": 2, "val_windows": 1, "rollout_frames": 2, "checkpoint_every_steps": 2,
                  "window": 3, "constraint_iterations": 4, "smoothing_iterations": 1, "init_from": ""},
        "model": {"encoder_levels": 1, "decoder_layers": 1, "decoder_ffn_hidden": 32},
        "baselines": {**TINY_BASELINES, "names": ["robocraft"]}}

pytestmark = pytest.mark.slow

RUN = "runs/tiny"
STORE = f"{RUN}/data/source/trajectories.zarr"
OUTPUTS = [STORE, f"{RUN}/models/worldcontact", f"{RUN}/models/baselines", f"{RUN}/reports/train.json"]
ENV = {**os.environ, "HF_HUB_OFFLINE": "1", "PUSH": "1", "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t",
       "GIT_COMMITTER_NAME": "t", "GIT_COMMITTER_EMAIL": "t@t"}
ENV.pop("WHEELS", None)


def sh(cwd: Path, *cmd: str) -> str:
    """Run a command in `cwd` (the checkout's own code first on the path); its output, or the test fails with it."""
    done = subprocess.run(cmd, cwd=cwd, env={**ENV, "PYTHONPATH": str(cwd)}, capture_output=True, text=True)
    assert done.returncode == 0, f"{' '.join(cmd)} -> {done.returncode}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done.stdout + done.stderr


def skipped(stage: str) -> str:
    """What `dvc repro` (run in the run folder) prints for a stage that its lock records as done."""
    return f"Stage '{stage}' didn't change, skipping"


def running(stage: str) -> str:
    return f"Running stage '{stage}'"


def dvc(cwd: Path, *args: str) -> str:
    return sh(cwd, str(cwd / ".venv/bin/python"), "-m", "dvc", *args)


def link_environment(repo: Path) -> None:
    """This checkout's .venv, linked (and kept out of git: `/.venv/` ignores the folder, not a link)."""
    (repo / ".venv").symlink_to(ROOT / ".venv")
    (repo / ".git" / "info").mkdir(parents=True, exist_ok=True)
    (repo / ".git" / "info" / "exclude").write_text("/.venv\n")


def checkout(src: Path, dest: Path, remote: Path) -> Path:
    """`dest` as a fresh clone of `src` with the project's .venv and its default remote `storage` at `remote`."""
    sh(dest.parent, "git", "clone", "-q", str(src), str(dest))
    link_environment(dest)
    dvc(dest, "remote", "modify", "--local", "storage", "url", str(remote))
    return dest


def same_bytes(a: Path, b: Path) -> bool:
    if a.is_file():
        return filecmp.cmp(a, b, shallow=False)
    ours = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    return ours == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file()) and all(
        filecmp.cmp(a / p, b / p, shallow=False) for p in ours)


@pytest.fixture(scope="module")
def project(tmp_path_factory, synthetic_store) -> Path:
    """A git repository of the project's files (as a clone of this checkout would hold them) with a run folder of
    train and train_baselines whose input store is a `dvc add`ed synthetic one."""
    repo = tmp_path_factory.mktemp("project") / "repo"
    files = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                           capture_output=True, text=True, check=True).stdout.split()
    for name in files:
        if (ROOT / name).is_file() and not name.startswith(("runs/", "tests/", "reports/", "docs/", "benchmarks/")):
            (repo / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, repo / name)
    (repo / RUN).mkdir(parents=True)
    config = {"extends": "../../params.yaml",
              "pipeline": {"targets": ["train", "train_baselines"], "inputs": ["data/source/trajectories.zarr"]},
              **TINY}
    (repo / RUN / "config.yaml").write_text(yaml.safe_dump(config))
    params = load_params("train.init_from=''")
    store = synthetic_store(params, EPISODES, frames=10)
    shutil.copytree(store, repo / STORE)
    sh(repo, "git", "init", "-q")
    link_environment(repo)
    dvc(repo, "add", STORE)
    dvc(repo, "remote", "modify", "--local", "storage", "url", str(repo.parent / "remote"))
    sh(repo, "git", "add", "-A")
    sh(repo, "git", "commit", "-qm", "the project and a tiny run folder")
    return repo


def test_the_default_remote_is_a_folder_outside_the_repository():
    config = (ROOT / ".dvc" / "config").read_text()
    assert "remote = storage" in config and "url = ~/.cache/worldcontact-dvc-remote" in config


def test_a_run_resumes_stage_by_stage_and_round_trips_through_the_remote(project):
    """A run cut short after train on one machine goes on from its lock on another (a fresh clone: git's record,
    DVC's remote), then a third clone pulls the whole run and finds it unchanged, byte for byte."""
    driver = ["bash", "scripts/gpu/run_pipeline.sh", "run", RUN]
    first = sh(project, *driver, "train")  # a run cut short: train only, pushed to the remote
    assert running("train") in first and running("train_baselines") not in first
    assert list(yaml.safe_load((project / RUN / "dvc.lock").read_text())["stages"]) == ["train"]
    assert all(s["frozen"] for s in yaml.safe_load((project / RUN / "dvc.yaml").read_text())["stages"].values())
    sh(project, "git", "add", "-A")
    sh(project, "git", "commit", "-qm", "the tiny run, up to train")

    remote = project.parent / "remote"
    second = checkout(project, project.parent / "second", remote)
    assert not (second / RUN / "models/worldcontact").exists()  # git holds the record, not the artefacts
    rest = sh(second, *driver)  # train's lock entry matches: skipped; train_baselines pulls its input and runs
    assert skipped("train") in rest and running("train_baselines") in rest
    assert sorted(yaml.safe_load((second / RUN / "dvc.lock").read_text())["stages"]) == ["train", "train_baselines"]
    sh(second, "git", "add", "-A")
    sh(second, "git", "commit", "-qm", "the tiny run's record")

    third = checkout(second, project.parent / "third", remote)
    dvc(third, "pull", f"{RUN}/dvc.yaml", f"{STORE}.dvc")
    assert "Data and pipelines are up to date" in dvc(third, "status", f"{RUN}/dvc.yaml", f"{STORE}.dvc")
    assert same_bytes(project / OUTPUTS[1], third / OUTPUTS[1])  # the model trained on the first machine
    for path in OUTPUTS[:1] + OUTPUTS[2:]:
        assert same_bytes(second / path, third / path), path
    again = sh(third, *driver)
    assert "Running stage" not in again and skipped("train_baselines") in again


def test_force_reruns_a_record_whose_outputs_no_remote_holds(project):
    """A committed record on a machine whose remote lacks its outputs (a bare GPU machine, say): a plain run skips
    the recorded stage and leaves no output; FORCE=1 reruns it."""
    driver = ["bash", "scripts/gpu/run_pipeline.sh", "run", RUN, "train"]
    sh(project, *driver)
    sh(project, "git", "add", "-A")
    sh(project, "git", "commit", "-q", "--allow-empty", "-m", "the tiny run's train record")
    lonely = project.parent / "lonely"  # a remote with the run's input store only
    dvc(project, "remote", "add", "--local", "-f", "lonely", str(lonely))
    dvc(project, "push", "-r", "lonely", f"{STORE}.dvc")
    fresh = checkout(project, project.parent / "fresh", lonely)
    assert skipped("train") in sh(fresh, "env", "PUSH=0", *driver) and not (fresh / OUTPUTS[1]).exists()
    assert running("train") in sh(fresh, "env", "PUSH=0", "FORCE=1", *driver)
    assert (fresh / OUTPUTS[1]).exists()


def wheel_file(folder: Path, name: str) -> None:
    """A minimal pure-Python wheel of package `name` (as `pip download` leaves one) in `folder`."""
    import zipfile  # noqa: PLC0415

    info = f"{name}-0.1.dist-info"
    with zipfile.ZipFile(folder / f"{name}-0.1-py3-none-any.whl", "w") as whl:
        whl.writestr(f"{name}/__init__.py", "WHEEL = True\n")
        whl.writestr(f"{info}/METADATA", f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.1\n")
        whl.writestr(f"{info}/WHEEL", "Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n")
        whl.writestr(f"{info}/RECORD", "")


def packed_wheels(folder: Path) -> Path:
    """Wheels for an offline machine in both forms the driver takes: a pack (an xz tar of tmp/site/<packages> split
    into part-NN pieces, one folder each) of one tiny package, and a wheel file of another."""
    site = folder / "tmp" / "site" / "wheel_probe"
    site.mkdir(parents=True)
    (site / "__init__.py").write_text("PACKED = True\n")
    sh(folder, "bash", "-c", "tar cf - tmp/site | xz -0 | split -b 100 -d - part- && n=1 && "
                             "for p in part-*; do mkdir $n && mv $p $n/ && n=$((n + 1)); done && rm -r tmp")
    assert len(list(folder.glob("*/part-*"))) > 1  # several, in numbered folders: .gpu/1/part-00, .gpu/2/part-01...
    wheel_file(folder / "1", "wheel_file_probe")
    return folder


def test_a_run_travels_as_pieces_to_a_checkout_with_no_remote(project, tmp_path):
    """pack / unpack: a run stopped after train on one machine is handed over as small files (its record and the
    objects of its outputs and input) to a checkout with no git, no remote and no .venv (a base interpreter plus
    packed wheels), where it goes on: train is skipped, train_baselines takes the store from the unpacked objects."""
    sh(project, "bash", "scripts/gpu/run_pipeline.sh", "run", RUN, "train")  # as the first machine left it
    sh(project, "bash", "scripts/gpu/run_pipeline.sh", "pack", RUN, str(tmp_path / "pieces"))
    pieces = sorted((tmp_path / "pieces").iterdir())
    assert pieces and all(p.name.startswith("run.tar.") for p in pieces)
    bare = project.parent / "bare"
    shutil.copytree(project, bare, symlinks=True, ignore=shutil.ignore_patterns(".git", "cache", "tmp", "config.local"))
    for path in [*OUTPUTS[:2], f"{RUN}/reports", f"{RUN}/dvc.lock"]:  # what the pieces bring
        shutil.rmtree(bare / path) if (bare / path).is_dir() else (bare / path).unlink()
    (bare / ".dvc" / "config.local").write_text(f"['remote \"storage\"']\n    url = {tmp_path / 'nowhere'}\n")
    (bare / ".venv").unlink()
    sh(bare, "bash", "scripts/gpu/run_pipeline.sh", "unpack", str(tmp_path / "pieces"))
    assert (bare / RUN / "dvc.lock").read_bytes() == (project / RUN / "dvc.lock").read_bytes()
    assert same_bytes(project / OUTPUTS[3], bare / OUTPUTS[3])  # a report: part of the record
    wheels = packed_wheels(tmp_path / "wheels")
    out = sh(bare, "env", "PUSH=0", f"WHEELS={wheels}", f"BASE_PYTHON={ROOT / '.venv/bin/python'}",
             "bash", "scripts/gpu/run_pipeline.sh", "run", RUN)  # no git either: DVC without an SCM
    assert skipped("train") in out and running("train_baselines") in out
    assert (bare / OUTPUTS[0]).is_dir() and same_bytes(project / OUTPUTS[0], bare / OUTPUTS[0])  # pulled from the pieces
    probe = "import wheel_probe, wheel_file_probe, dvc; print(wheel_probe.PACKED, wheel_file_probe.WHEEL)"
    assert sh(bare, ".venv/bin/python", "-c", probe).strip() == "True True"
    dvc(bare, "checkout", f"{RUN}/dvc.yaml:train")  # train's model, from the unpacked objects
    assert same_bytes(project / OUTPUTS[1], bare / OUTPUTS[1])
