"""The one front end of every stage: `stages/<name>.py` declares a `StageCommand`, which parses the flags, reads
the params, calls the stage's work function in wc/... and prints its summary line(s).

    COMMAND = StageCommand("validate", __doc__, validate, validate_summary, VALIDATE)
    main = COMMAND.main
    if __name__ == "__main__":
        COMMAND.cli()
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, field
from typing import Any

from wc.cli import run_cli
from wc.config import add_params_arguments, read_params

Report = dict[str, Any]
Options = Mapping[str, Mapping[str, Any]]  # argparse name or flag -> add_argument keywords


def params_from_args(args: argparse.Namespace) -> Report:
    """The params of `--params FILE` with the `--set` overrides applied (the default `StageCommand.params`)."""
    return read_params(args.params, args.overrides)


def flag(key: str) -> str:
    """The flag of a work function's path keyword: `stability_csv` -> `--stability-csv`."""
    return "--" + key.replace("_", "-")


@dataclass(frozen=True)
class StageCommand:
    """A stage's command line, in this order: `--params` / `--set` (unless `params` is None), `params_options`
    (read by `params` only), one `--<key>` per entry of `paths` (key -> default path, help from `helps`), then
    `options`. `main` calls `work(params, **paths, **options)` (keywords: the argparse dests, or their name in
    `keywords`; no params when `params` is None; '' passed as None for the `optional` paths), prints
    `summary(report)` (nothing when empty) and exits with `exit_status(report)` when that is non-zero."""

    name: str
    doc: str | None
    work: Callable[..., Report]
    summary: Callable[[Report], str]
    paths: Mapping[str, str] = field(default_factory=dict)
    options: Options = field(default_factory=dict)
    helps: Mapping[str, str] = field(default_factory=dict)
    keywords: Mapping[str, str] = field(default_factory=dict)  # dest -> the work's keyword, where they differ
    optional: Collection[str] = ()
    params: Callable[[argparse.Namespace], Report] | None = params_from_args
    params_options: Options = field(default_factory=dict)
    check: Callable[[argparse.Namespace], str | None] | None = None  # a usage error, before anything runs
    exit_status: Callable[[Report], int] | None = None
    expected: tuple[type[BaseException], ...] = ()  # more errors that end in one line (wc.cli)

    def parser(self) -> tuple[argparse.ArgumentParser, list[str]]:
        """The argument parser, and the dests of the arguments the work function takes."""
        parser = argparse.ArgumentParser(description=self.doc, formatter_class=argparse.RawDescriptionHelpFormatter)
        if self.params is not None:
            add_params_arguments(parser)
        for name, spec in self.params_options.items():
            parser.add_argument(name, **spec)
        dests = [parser.add_argument(flag(key), default=default, help=self.helps.get(key)).dest
                 for key, default in self.paths.items()]
        return parser, dests + [parser.add_argument(name, **spec).dest for name, spec in self.options.items()]

    def main(self, argv: list[str] | None = None) -> Report:
        """Parse `argv` (default: sys.argv[1:]), run the work, print the summary; returns the work's report."""
        parser, dests = self.parser()
        args = parser.parse_args(argv)
        if self.check is not None and (problem := self.check(args)):
            parser.error(problem)
        kwargs = {self.keywords.get(d, d): None if d in self.optional and getattr(args, d) == "" else getattr(args, d)
                  for d in dests}
        report = self.work(**kwargs) if self.params is None else self.work(self.params(args), **kwargs)
        if text := self.summary(report):
            print(text)
        if self.exit_status is not None and (status := self.exit_status(report)):
            sys.exit(status)
        return report

    def cli(self) -> None:
        """`python -m stages.<name>`: `main()` with its expected errors as one line on stderr (wc.cli.run_cli)."""
        run_cli(self.main, self.name, self.expected)
