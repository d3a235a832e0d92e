"""A run folder (`runs/<name>/`): one configuration of the pipeline, run by DVC as a pipeline of its own, its params,
lock and outputs kept apart from the CPU default's (the root params.yaml, dvc.yaml and dvc.lock stay untouched).

`runs/<name>/config.yaml` is the hand-written part: a params override file (`extends: [../../params.yaml, ...]`,
wc.config.read_params) plus `pipeline: {targets: [...], inputs: [...]}`: the root dvc.yaml stages the run ends with,
and optionally paths the run takes as given (e.g. a store put into the folder with `dvc add`) instead of from the
stage that makes them.
`python -m wc.run_folder runs/<name>` writes beside it:

    params.yaml  the resolved params: every value, as the stages read them and as DVC tracks them
    dvc.yaml     the root dvc.yaml's stages the targets need (their upstream stages too), run in the folder: the
                 commands and outputs as in the root, relative to the folder; code and shipped inputs (no stage
                 makes them) read from the repository (`../../wc/...`); the root's plots of those outputs
    .gitignore   the outputs DVC caches, so git keeps only the record, also where DVC ran without git

`dvc repro runs/<name>/dvc.yaml` then writes runs/<name>/dvc.lock, the run's record (docs/versioning.md).
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

import yaml

from wc.cli import run_cli
from wc.config import ParamsError, read_params

CONFIG = "config.yaml"
IGNORE = ".gitignore"  # the run's cached outputs (cached_outputs), written with params.yaml and dvc.yaml
PYTHON = ".venv/bin/python"  # how every root stage command starts
HEADER = ("# Written by `python -m wc.run_folder {folder}` from {config} and the root dvc.yaml; edit those, not this"
          " file.\n")


def _names(value: Any) -> bool:
    return isinstance(value, list) and all(isinstance(v, str) and v for v in value)


def resolve_config(config: Path) -> tuple[dict[str, Any], list[str], list[str]]:
    """The run's resolved params (plain YAML types, no `pipeline` section), `pipeline.targets` and
    `pipeline.inputs`."""
    params = read_params(config)
    params.pop("_source")
    pipeline = params.pop("pipeline", None)
    pipeline = pipeline if isinstance(pipeline, dict) else {}
    targets, inputs = pipeline.get("targets"), pipeline.get("inputs", [])
    if not _names(targets) or not targets:
        raise ParamsError(f"{config}: pipeline.targets must list the root dvc.yaml stages the run ends with, "
                          f"got {targets!r}")
    if not _names(inputs):
        raise ParamsError(f"{config}: pipeline.inputs must list paths the run takes as given, got {inputs!r}")
    unknown = sorted(set(pipeline) - {"targets", "inputs"})
    if unknown:
        raise ParamsError(f"{config}: unknown key pipeline.{unknown[0]} (expected targets, inputs)")
    return json.loads(json.dumps(params)), targets, inputs


def _name(entry: str | dict[str, Any]) -> str:
    return entry if isinstance(entry, str) else next(iter(entry))


def _foreach_items(stage: dict[str, Any], params: dict[str, Any]) -> list[tuple[str, Any]]:
    """(key, item) per instance of a `foreach: ${section}` stage, from the run's params ([("", None)] if none)."""
    spec = stage.get("foreach")
    if spec is None:
        return [("", None)]
    values = params.get(str(spec).removeprefix("${").removesuffix("}")) if isinstance(spec, str) else spec
    if isinstance(values, dict):
        return [(str(k), v) for k, v in values.items()]
    return [(str(v), v) for v in values or []]


def _entries(stage: dict[str, Any], fields: tuple[str, ...], params: dict[str, Any]) -> list[tuple[str, dict]]:
    """(path, options) of what a stage lists under `fields`, every foreach instance's (${key} / ${item} filled in)."""
    body = stage.get("do", stage)
    listed = [(_name(e), (e[_name(e)] if isinstance(e, dict) else None) or {}) for f in fields for e in body.get(f, [])]
    return [(path.replace("${key}", key).replace("${item}", str(item)), options)
            for key, item in _foreach_items(stage, params) for path, options in listed]


def _paths(stage: dict[str, Any], fields: tuple[str, ...], params: dict[str, Any]) -> list[str]:
    """The paths a stage lists under `fields` (see _entries)."""
    return [path for path, _ in _entries(stage, fields, params)]


def _overlap(a: str, b: str) -> bool:
    """Whether one path is the other or lies inside it."""
    a, b = a.rstrip("/"), b.rstrip("/")
    return a == b or a.startswith(b + "/") or b.startswith(a + "/")


OUTPUTS = ("outs", "metrics", "plots")


def needed_stages(stages: dict[str, Any], targets: list[str], params: dict[str, Any],
                  inputs: list[str] = ()) -> list[str]:
    """The targets and every stage upstream of them (a stage whose outputs one of theirs depends on, unless that dep
    is one of `inputs`), in the root dvc.yaml's order."""
    unknown = [t for t in targets if t not in stages]
    if unknown:
        raise ParamsError(f"pipeline.targets: no stage {unknown[0]!r} in dvc.yaml (stages: {', '.join(stages)})")
    outs = {name: _paths(stage, OUTPUTS, params) for name, stage in stages.items()}
    needed, todo = set(), list(targets)
    while todo:
        name = todo.pop()
        if name in needed:
            continue
        needed.add(name)
        deps = [d for d in _paths(stages[name], ("deps",), params) if not any(_overlap(d, i) for i in inputs)]
        todo += [other for other, made in outs.items() if any(_overlap(d, o) for d in deps for o in made)]
    return [name for name in stages if name in needed]


def run_stage(stage: dict[str, Any], up: str, made: list[str]) -> dict[str, Any]:
    """A root stage as the run folder runs it: its command through `up`/.venv, its deps that no stage makes (code,
    shipped inputs) read from the repository `up` levels above; everything else as in the root, relative to the
    folder."""
    stage = json.loads(json.dumps(stage))
    body = stage.get("do", stage)
    if "wdir" in body:
        raise ParamsError("dvc.yaml: a stage with its own wdir cannot run in a run folder")
    if not body["cmd"].startswith(PYTHON + " "):
        raise ParamsError(f"dvc.yaml: a stage command must start with {PYTHON}, got {body['cmd'][:60]!r}")
    body["cmd"] = f"{up}/{body['cmd']}"

    def located(entry: str | dict[str, Any]) -> str | dict[str, Any]:
        path = _name(entry)
        if any(_overlap(path, m) for m in made):
            return entry
        return f"{up}/{path}" if isinstance(entry, str) else {f"{up}/{path}": entry[path]}

    body["deps"] = [located(d) for d in body.get("deps", [])]
    return stage


def _plot_files(entry: dict[str, Any]) -> set[str]:
    """The files a top-level plot draws: its key, or the files its x / y mappings name."""
    name, props = next(iter(entry.items()))
    files = {f for axis in ("x", "y") if isinstance((props or {}).get(axis), dict) for f in props[axis]}
    return files or {name}


def run_pipeline(root: dict[str, Any], targets: list[str], params: dict[str, Any], up: str,
                 inputs: list[str] = ()) -> dict[str, Any]:
    """The run folder's dvc.yaml: the stages the targets need (run_stage) and the root's plots of their outputs."""
    stages = root["stages"]
    names = needed_stages(stages, targets, params, inputs)
    made = [p for stage in stages.values() for p in _paths(stage, OUTPUTS, params)]
    ours = [p for n in names for p in _paths(stages[n], OUTPUTS, params)]
    pipeline: dict[str, Any] = {"stages": {n: run_stage(stages[n], up, made) for n in names}}
    plots = [e for e in root.get("plots", []) if _plot_files(e) <= set(ours)]
    if plots:
        pipeline["plots"] = plots
    return pipeline


def write_run_folder(folder: str | Path, root: str | Path = ".", frozen: bool = True) -> dict[str, Any]:
    """Write `folder`/params.yaml and `folder`/dvc.yaml from `folder`/config.yaml and `root`/dvc.yaml; returns what
    was written. `frozen`: every stage of that dvc.yaml is frozen, so the root `dvc repro` (which collects every
    dvc.yaml of the repository) leaves the run alone; the driver writes it unfrozen to run it, then frozen again."""
    folder, root = Path(folder), Path(root)
    config = folder / CONFIG
    if not config.is_file():
        raise FileNotFoundError(f"run_folder: no {config} (a run folder holds its config.yaml)")
    up = Path(os.path.relpath(root.resolve(), folder.resolve())).as_posix()
    if not set(Path(up).parts) <= {".."}:
        raise ParamsError(f"run_folder: {folder} is not inside the repository {root.resolve()}")
    params, targets, inputs = resolve_config(config)
    pipeline = run_pipeline(yaml.safe_load((root / "dvc.yaml").read_text()), targets, params, up, inputs)
    for stage in pipeline["stages"].values():
        stage["frozen"] = frozen
    header = HEADER.format(folder=folder.as_posix(), config=CONFIG)
    for name, data in (("params.yaml", params), ("dvc.yaml", pipeline)):
        (folder / name).write_text(header + yaml.safe_dump(data, sort_keys=False, width=120))
    (folder / IGNORE).write_text(header + "".join(f"/{path}\n" for path in cached_outputs(pipeline, params)))
    return {"folder": str(folder), "stages": list(pipeline["stages"]), "targets": targets}


def cached_outputs(pipeline: dict[str, Any], params: dict[str, Any], cached: bool = True) -> list[str]:
    """The outputs of a run's stages that DVC caches (or, `cached` false, those it does not: git keeps them),
    relative to the run folder. The folder's .gitignore lists the cached ones, so a run made where DVC has no git (a
    GPU machine's copy, `core.no_scm`) is committed without them."""
    return [path for stage in pipeline["stages"].values()
            for path, options in _entries(stage, OUTPUTS, params) if (options.get("cache") is not False) is cached]


def record_files(folder: str | Path) -> list[str]:
    """The run's record, what git keeps of it: config.yaml, params.yaml, dvc.yaml, dvc.lock and the outputs DVC does
    not cache (its reports), those that exist, as paths under `folder`."""
    folder = Path(folder)
    params = yaml.safe_load((folder / "params.yaml").read_text())
    outs = cached_outputs(yaml.safe_load((folder / "dvc.yaml").read_text()), params, cached=False)
    names = [CONFIG, "params.yaml", "dvc.yaml", IGNORE, "dvc.lock", *outs]
    return [(folder / n).as_posix() for n in names if (folder / n).is_file()]


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", help="the run folder, e.g. runs/gpu_policy (holding config.yaml)")
    parser.add_argument("--root", default=".", help="the repository root (default: the current directory)")
    parser.add_argument("--record", action="store_true",
                        help="print the run's record files (one a line) instead of writing params.yaml and dvc.yaml")
    parser.add_argument("--unfrozen", action="store_true",
                        help="write dvc.yaml with its stages unfrozen, to run them (the default freezes them)")
    args = parser.parse_args(argv)
    if args.record:
        files = record_files(args.folder)
        print("\n".join(files))
        return {"folder": args.folder, "record": files}
    written = write_run_folder(args.folder, args.root, frozen=not args.unfrozen)
    print(f"run_folder: {written['folder']}: params.yaml, dvc.yaml with {len(written['stages'])} "
          f"{'unfrozen' if args.unfrozen else 'frozen'} stages ({', '.join(written['stages'])})")
    return written


if __name__ == "__main__":
    run_cli(main, "run_folder")
