"""Push a LeRobot dataset to the Hugging Face Hub.

    python -m stages.push data/lerobot/expanded --repo-id user/name [--private]

Needs a token (`hf auth login` or HF_TOKEN) and network; offline (HF_HUB_OFFLINE=1), without a token
or without network it exits non-zero with a one-line message. Not a DVC stage: publishing is a choice.
"""

from __future__ import annotations

import argparse

from wc.cli import run_cli
from wc.policy.hub import PushError, push_dataset


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("root", help="local LeRobot dataset folder, e.g. data/lerobot/expanded")
    parser.add_argument("--repo-id", required=True, help="Hub dataset repo, e.g. user/worldcontact-lift")
    parser.add_argument("--private", action="store_true", help="create the repo private")
    args = parser.parse_args(argv)
    try:
        url = push_dataset(args.root, args.repo_id, private=args.private)
    except PushError as err:
        raise SystemExit(f"push: {err}") from None
    print(f"push: {args.root} -> {url}")


if __name__ == "__main__":
    run_cli(main, "push")
