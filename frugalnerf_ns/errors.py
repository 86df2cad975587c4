"""The one way FrugalNeRF reports something a user can fix: one line, exit status 1, no traceback.

Library code raises ``UserError`` (an ordinary Exception, so callers can catch it); the places where
nerfstudio's commands enter our code (the pipeline's and the trainer's set-up, the training loop, checkpoint
loading for the evaluation tools) turn it into a SystemExit carrying the same line (``one_line_errors``),
which nerfstudio's commands print before exiting with status 1.
"""

from __future__ import annotations

import contextlib
from typing import Iterator


class UserError(Exception):
    """``frugalnerf: error: <message>``; subclasses say what kind of input was wrong (data, options,
    checkpoints)."""

    def __init__(self, message: str) -> None:
        super().__init__(f"frugalnerf: error: {message}")


@contextlib.contextmanager
def one_line_errors() -> Iterator[None]:
    """At a command boundary: a UserError ends the command with its line and exit status 1."""
    try:
        yield
    except UserError as err:
        raise SystemExit(str(err)) from None
