"""The one way FrugalNeRF stops on something a user can fix: one line, exit status 1, no traceback."""

from __future__ import annotations


class UserError(SystemExit):
    """A SystemExit carrying ``frugalnerf: error: <message>``: nerfstudio's commands print it and exit with 1.
    Subclasses say what kind of input was wrong (data, options, checkpoints)."""

    def __init__(self, message: str) -> None:
        super().__init__(f"frugalnerf: error: {message}")
