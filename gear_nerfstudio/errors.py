"""Bad input the user can fix, and how it is reported: one line, no traceback.

Every error of this project about its input (data files, options, model files, clicks, camera paths) is an
``InputError``. nerfstudio's commands (ns-train, ns-eval, ns-render, ns-viewer) run the plugin inside their own
code, so the plugin reports these errors where Python would print a traceback: ``report_input_errors``
(installed when the package is imported) prints ``error: <message>`` for an ``InputError`` that reaches the top
of a command and leaves every other exception to the hook that was there before.
"""

from __future__ import annotations

import sys


class InputError(ValueError):
    """Bad input; the message names the file or option and what is wrong with it."""


def report_input_errors() -> None:
    """Install the one-line report of ``InputError`` as ``sys.excepthook`` (once)."""
    previous = sys.excepthook
    if getattr(previous, "reports_input_errors", False):
        return

    def hook(kind, error, traceback) -> None:
        if isinstance(error, InputError):
            print(f"error: {error}", file=sys.stderr)
        else:
            previous(kind, error, traceback)

    hook.reports_input_errors = True
    sys.excepthook = hook
