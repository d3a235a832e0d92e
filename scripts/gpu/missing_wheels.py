"""The pip specs an offline machine lacks for this project: the dependency closure of the project's requirements (or
of the packages named), at the versions installed in this checkout's .venv (requirements.lock), minus the packages
the machine already has. Feed them to ../shared/gpu/pack-wheels.sh; scripts/gpu/run_pipeline.sh (WHEELS=DIR) unpacks
the parts there.

    python3 -m pip list --format=freeze > have.txt                 # on the machine (or a list of names, one a line)
    .venv/bin/python scripts/gpu/missing_wheels.py --have have.txt --skip ray > wheels.txt   # here
    ../shared/gpu/pack-wheels.sh $(cat wheels.txt)
"""

from __future__ import annotations

import argparse
import re
import sys
import tomllib
from importlib import metadata
from pathlib import Path

from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[2]


def canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def closure(specs: list[str]) -> dict[str, str]:
    """{canonical name: installed version} of the packages `specs` need, transitively, with their extras."""
    found: dict[str, str] = {}
    todo = [Requirement(s) for s in specs]
    seen: set[tuple[str, frozenset[str]]] = set()
    while todo:
        req = todo.pop()
        key = (canonical(req.name), frozenset(req.extras))
        if key in seen:
            continue
        seen.add(key)
        try:
            dist = metadata.distribution(req.name)
        except metadata.PackageNotFoundError:
            sys.exit(f"missing_wheels: error: {req.name} is not installed in {sys.prefix} (run scripts/install.sh)")
        found[canonical(req.name)] = dist.version
        for line in dist.requires or []:
            dep = Requirement(line)
            if dep.marker is None or any(dep.marker.evaluate({"extra": e}) for e in (*req.extras, "")):
                todo.append(dep)
    return found


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("specs", nargs="*", help="requirements (default: pyproject.toml's dependencies)")
    parser.add_argument("--have", type=Path, help="the machine's packages: `pip list --format=freeze` or names")
    parser.add_argument("--skip", nargs="*", default=[], help="packages to leave out with their own dependencies")
    args = parser.parse_args(argv)
    specs = args.specs or tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    skip = {canonical(s) for s in args.skip}
    specs = [s for s in specs if canonical(Requirement(s).name) not in skip]
    have = {canonical(re.split(r"[=<> ]", line.strip())[0]) for line in args.have.read_text().splitlines()
            if line.strip() and not line.startswith("#")} if args.have else set()
    for name, version in sorted(closure(specs).items()):
        if name not in have:
            print(f"{name}=={version}")


if __name__ == "__main__":
    main()
