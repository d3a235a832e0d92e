"""The documents a newcomer reads: every relative link resolves (anchors too), every documented stage flag is one the
stage takes, nothing is named after an issue number and no document speaks of sessions or issues, the README stays a
one-screen map and quotes the policy comparison as its report has it, and the paper, licence and citation agree."""

from __future__ import annotations

import importlib
import json
import re
import subprocess
from pathlib import Path

import pytest
import yaml

from tests.conftest import ROOT

DOCS = sorted([ROOT / "README.md", ROOT / "CITATION.cff", *(ROOT / "docs").glob("*.md"),
               *(ROOT / "models" / "pretrained").glob("*/README.md"), *(ROOT / "reports").glob("*.md"),
               *(ROOT / "reports" / "gpu").glob("*.md"), ROOT / "wc" / "baselines" / "README.md"])
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
PAPER = "WorldContact: A Contact-Centric World Model for Scalable Robot Learning"


def _anchors(markdown: str) -> set[str]:
    """GitHub's anchors of a Markdown file's headings."""
    heads = re.findall(r"^#{1,6} (.+)$", markdown, re.M)
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in heads}


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(doc: Path) -> None:
    text = doc.read_text()
    for target in LINK.findall(text):
        if re.match(r"[a-z]+://|mailto:", target):
            continue
        path, _, anchor = target.partition("#")
        file = (doc.parent / path).resolve() if path else doc
        assert file.exists(), f"{doc.relative_to(ROOT)}: link {target} does not resolve"
        if anchor and file.suffix == ".md":
            assert anchor in _anchors(file.read_text()), f"{doc.relative_to(ROOT)}: no heading for #{anchor} in {path}"


def _tracked() -> list[str]:
    return subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()


def test_nothing_is_named_after_an_issue_or_a_session() -> None:
    named = [p for p in _tracked() if re.search(r"(?i)(issue|session)[ _-]?\d", p)]
    assert not named, named


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_documents_speak_of_capabilities_not_of_sessions_or_issues(doc: Path) -> None:
    text = doc.read_text()
    found = re.findall(r"(?i)\bissue[ _#-]?\d+|\bsessions?\b|\b(?:first|second|third|fourth|fifth|sixth|seventh|eighth|"
                       r"ninth|tenth) session|\bour \d+-minute\b|GPU holds?\b", text)
    assert not found, f"{doc.relative_to(ROOT)}: {found}"


def test_the_readme_is_a_one_screen_map_that_gives_the_outcome() -> None:
    readme = (ROOT / "README.md").read_text()
    assert len(readme.split()) <= 2200
    arms = json.loads((ROOT / "reports" / "gpu" / "policy_h100_three_arms.json").read_text())["arms"]
    quoted = re.findall(r"in (\d+) of (\d+)", readme.split("**Outcome", 1)[1].split("\n\n", 1)[0])
    assert quoted == [(str(arms[a]["successes"]), str(arms[a]["trials"])) for a in ("source", "expanded", "newton_150")]


def test_the_paper_licence_and_citation_agree() -> None:
    readme = (ROOT / "README.md").read_text()
    citation = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert PAPER in readme and citation["preferred-citation"]["title"] == PAPER
    assert citation["license"] == "Apache-2.0" and "Apache License" in (ROOT / "LICENSE").read_text()
    assert re.search(r'^license = "Apache-2.0"$', (ROOT / "pyproject.toml").read_text(), re.M)
    assert len(citation["preferred-citation"]["authors"]) == 10


def _documented_stage_flags() -> set[tuple[str, str, str]]:
    """(document, stage, --flag) for every flag written after `python -m stages.<stage>` on one command line."""
    found = set()
    for doc in DOCS:
        for line in re.split(r"(?<!\\)\n", doc.read_text()):
            for stage, rest in re.findall(r"python -m stages\.(\w+)((?:[^`\n|]|\\\n)*)", line):
                found |= {(doc.name, stage, f) for f in re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)", rest)}
    return found


@pytest.mark.slow
def test_every_documented_stage_flag_is_one_the_stage_takes() -> None:
    documented = _documented_stage_flags()
    assert len({stage for _, stage, _ in documented}) >= 6
    for doc, stage, name in sorted(documented):
        parser, _ = importlib.import_module(f"stages.{stage}").COMMAND.parser()
        assert name in parser._option_string_actions, f"{doc}: python -m stages.{stage} has no {name}"
