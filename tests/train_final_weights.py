"""`python -m tests.train_final_weights DIR [stages.train arguments]`, alone or under torchrun: the train stage as
`python -m stages.train` runs it, then this process's WorldContact weights after its last step saved to
DIR/rank<RANK>.safetensors. What tests/test_train.py compares across the ranks of a DDP run, where only rank 0 writes
the stage's outputs.

The model is the one wc.train.loop builds: its constructor is wrapped to keep a reference, nothing else changes."""

from __future__ import annotations

import os
import sys
from pathlib import Path

from safetensors.torch import save_file

import wc.train.loop as loop
from stages.train import COMMAND


def main(argv: list[str]) -> None:
    out, stage_argv = Path(argv[0]), argv[1:]
    built = []
    construct = loop.WorldContact

    def kept(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        built.append(construct(*args, **kwargs))
        return built[-1]

    loop.WorldContact = kept
    COMMAND.main(stage_argv)
    (model,) = built
    state = {k: v.detach().clone() for k, v in model.state_dict().items()}
    save_file(state, str(out / f"rank{os.environ.get('RANK', '0')}.safetensors"))


if __name__ == "__main__":
    main(sys.argv[1:])
