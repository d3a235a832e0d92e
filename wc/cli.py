"""How a stage run from the command line ends on an error the user can fix: one line, not a traceback.

    if __name__ == "__main__":
        run_cli(main, "validate")

`run_cli` calls `main()`. An expected error (bad params, a missing or corrupt input, an output it refuses to
replace, an invalid value: `EXPECTED`, plus the classes a stage adds) prints the one line
`<stage>: error: <message>` (with the exception's notes, joined by "; ") to stderr and exits with status 2;
Ctrl-C exits with status 130. Any other exception is a bug and propagates with its traceback. `main` itself
keeps raising, for tests and other callers.

Environment: WC_TRACEBACK=1 re-raises expected errors too, with the full traceback (for debugging).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable

from wc.config import ParamsError

EXPECTED: tuple[type[BaseException], ...] = (ParamsError, FileNotFoundError, NotADirectoryError, FileExistsError,
                                             PermissionError, ValueError)  # ValueError: also a corrupt store
EXIT_ERROR, EXIT_INTERRUPTED = 2, 130


def error_line(stage: str, err: BaseException) -> str:
    """`<stage>: error: <message>; <note>; ...` on one line (the message without a repeated `<stage>: `)."""
    parts = [str(err) or type(err).__name__, *getattr(err, "__notes__", ())]
    text = "; ".join(" ".join(part.split()) for part in parts if part.strip())
    return f"{stage}: error: {text.removeprefix(f'{stage}: ')}"


def run_cli(main: Callable[[], object], stage: str, expected: tuple[type[BaseException], ...] = ()) -> None:
    """Run a stage's `main()`; an expected error (`EXPECTED` + the stage's own `expected`) or Ctrl-C ends it with
    one line on stderr (module docstring)."""
    try:
        main()
    except (*EXPECTED, *expected, KeyboardInterrupt) as err:
        if os.environ.get("WC_TRACEBACK", "") not in ("", "0"):
            raise
        interrupted = isinstance(err, KeyboardInterrupt)
        print(f"{stage}: error: interrupted" if interrupted else error_line(stage, err), file=sys.stderr, flush=True)
        sys.exit(EXIT_INTERRUPTED if interrupted else EXIT_ERROR)
