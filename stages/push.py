"""Push a LeRobot dataset to the Hugging Face Hub.

    python -m stages.push data/lerobot/expanded --repo-id user/name [--private]

Needs a token (`hf auth login` or HF_TOKEN) and network; offline (HF_HUB_OFFLINE=1), without a token
or without network it exits with status 2 and one line `push: error: ...`. Not a DVC stage: publishing is a choice.
"""

from wc.policy.hub import PushError, push
from wc.stage_cli import StageCommand

COMMAND = StageCommand(
    "push", __doc__, push, lambda r: f"push: {r['root']} -> {r['url']}", params=None,
    options={"root": {"help": "local LeRobot dataset folder, e.g. data/lerobot/expanded"},
             "--repo-id": {"required": True, "help": "Hub dataset repo, e.g. user/worldcontact-lift"},
             "--private": {"action": "store_true", "help": "create the repo private"}},
    expected=(PushError,))
main = COMMAND.main

if __name__ == "__main__":
    COMMAND.cli()
