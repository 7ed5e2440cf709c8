"""Progress of long runs on stderr: a bar with the count and the objective.

On a terminal the bar is one line rewritten in place and ended by the last report (or by the
next message); elsewhere (a log file, CI) every report is a line of its own, so that a log
keeps the objective's history.
"""

from __future__ import annotations

import sys

_WIDTH = 20
_open = False  # a terminal line written in place and not yet ended


def _terminal() -> bool:
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # a replaced or closed stream
        return False


def bar(label: str, done: int, total: int, text: str, unit: str = "step") -> None:
    """Report ``done`` of ``total`` (steps, evaluations) of the run ``label``, with ``text``
    (the objective), e.g. ``tune_local [██████░░░░░░░░░░░░░░] step 90/300, J mean 1.09``."""
    global _open
    filled = min(_WIDTH, max(0, round(_WIDTH * done / max(total, 1))))
    line = f"{label} [{'█' * filled}{'░' * (_WIDTH - filled)}] {unit} {done}/{total}, {text}"
    if _terminal():
        last = done >= total
        sys.stderr.write("\r\x1b[2K" + line + ("\n" if last else ""))
        _open = not last
    else:
        sys.stderr.write(line + "\n")
    sys.stderr.flush()


def say(text: str) -> None:
    """One message line (ends a bar left open on a terminal)."""
    global _open
    if _open:
        sys.stderr.write("\n")
        _open = False
    sys.stderr.write(text + "\n")
    sys.stderr.flush()
