"""Upload a local LeRobot dataset to the Hugging Face Hub with `LeRobotDataset.push_to_hub`."""

from __future__ import annotations

import re
from pathlib import Path


_REPO_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*/[A-Za-z0-9][A-Za-z0-9_.-]*$")


class PushError(RuntimeError):
    """The dataset cannot be pushed (no dataset, offline, no token, no network, refused by the Hub)."""


def _card_description(root: Path) -> str | None:
    """Our card's text, passed to LeRobot's card template (push_to_hub replaces README.md with that card)."""
    from wc.policy.dataset import CARD_FILE

    card = root / CARD_FILE
    return card.read_text() if card.is_file() else None


def push_dataset(root: str | Path, repo_id: str, private: bool = False) -> str:
    """Push the dataset at `root` to the Hub as `repo_id`; returns its URL. Raises PushError with a
    one-line reason when it is offline (HF_HUB_OFFLINE), has no token or cannot reach the Hub."""
    import httpx
    from huggingface_hub import get_token, is_offline_mode
    from huggingface_hub.errors import HfHubHTTPError, OfflineModeIsEnabled

    root = Path(root)
    if not _REPO_ID_RE.match(repo_id):
        raise PushError(f"--repo-id must be <user or org>/<name>, got {repo_id!r}")
    if not (root / "meta" / "info.json").is_file():
        raise PushError(f"{root} is not a LeRobot dataset (no meta/info.json); build it with `python -m stages.dataset`")
    if is_offline_mode():
        raise PushError("HF_HUB_OFFLINE is set: cannot push while offline (unset HF_HUB_OFFLINE and retry)")
    if not get_token():
        raise PushError("no Hugging Face token: run `hf auth login` or set HF_TOKEN, then retry")
    from lerobot.datasets.lerobot_dataset import LeRobotDataset  # slow imports: after the cheap checks

    from wc.policy.dataset import VIDEO_BACKEND

    dataset = LeRobotDataset(repo_id, root=root, video_backend=VIDEO_BACKEND)
    try:
        dataset.push_to_hub(private=private, dataset_description=_card_description(root))
    except (httpx.TransportError, OfflineModeIsEnabled, OSError) as err:
        raise PushError(f"cannot reach the Hugging Face Hub ({type(err).__name__}: {err}); check the network") from err
    except HfHubHTTPError as err:
        reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise PushError(f"the Hub refused the push of {repo_id}: {reason}") from err
    return f"https://huggingface.co/datasets/{repo_id}"


def push(root: str, repo_id: str, private: bool = False) -> dict[str, str]:
    """`push_dataset` as `python -m stages.push` runs it: a PushError is an expected error, ending the command with
    `push: error: <reason>` and status 2 (wc.cli)."""
    return {"root": root, "url": push_dataset(root, repo_id, private=private)}
