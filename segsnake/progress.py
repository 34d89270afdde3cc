"""A dependency-free progress display for long runs, written to stderr.

On a terminal it draws one self-overwriting bar line; in a log (stderr not a terminal) it writes one
line per finished item instead, so batch jobs on a cluster still leave a readable trace; ``quiet``
silences both. Only the edges (``commands``, ``batch``) use it: the numerical core never prints.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

__all__ = ["ProgressBar"]


def _fmt_seconds(s: float) -> str:
    s = int(round(s))
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s // 3600}h{(s % 3600) // 60:02d}m"


class ProgressBar:
    """Count finished items out of ``total`` and show it on ``stream``.

    Parameters
    ----------
    total : int
        Number of items.
    label : str
        Word shown before the counter (``"cases"``).
    initial : int
        Items already done before this run (a resumed batch).
    quiet : bool
        Show nothing at all.
    stream : text stream, optional
        Defaults to ``sys.stderr`` (looked up at construction, so tests can redirect it).
    mode : {"auto", "bar", "lines", "off"}
        ``auto`` picks ``bar`` on a terminal and ``lines`` otherwise.
    width : int
        Width of the bar in characters.
    """

    def __init__(self, total: int, *, label: str = "items", initial: int = 0, quiet: bool = False,
                 stream: TextIO | None = None, mode: str = "auto", width: int = 30) -> None:
        self.total = max(0, int(total))
        self.done = max(0, int(initial))
        self.label = label
        self.stream = sys.stderr if stream is None else stream
        if quiet:
            mode = "off"
        elif mode == "auto":
            isatty = getattr(self.stream, "isatty", None)
            mode = "bar" if callable(isatty) and isatty() else "lines"
        if mode not in ("bar", "lines", "off"):
            raise ValueError(f"unknown progress mode {mode!r}")
        self.mode = mode
        self.width = width
        self._start = time.monotonic()
        self._initial = self.done
        self._drawn = False
        if self.mode == "bar":
            self._draw("")

    def _eta(self) -> str:
        ran = self.done - self._initial
        left = self.total - self.done
        if ran <= 0 or left <= 0:
            return ""
        return f" eta {_fmt_seconds((time.monotonic() - self._start) / ran * left)}"

    def _draw(self, note: str) -> None:
        frac = self.done / self.total if self.total else 1.0
        filled = int(round(frac * self.width))
        bar = "#" * filled + "-" * (self.width - filled)
        line = f"[{bar}] {self.done}/{self.total} {self.label}{self._eta()}"
        if note:
            line += f"  {note}"
        # \r + clear-to-end-of-line redraws in place without leaving stale characters.
        self.stream.write("\r" + line[:200] + "\033[K")
        self.stream.flush()
        self._drawn = True

    def update(self, n: int = 1, note: str = "") -> None:
        """Mark ``n`` more items finished; ``note`` names the last one (e.g. ``"case7 ok"``)."""
        self.done = min(self.total, self.done + n) if self.total else self.done + n
        if self.mode == "bar":
            self._draw(note)
        elif self.mode == "lines":
            text = f"[{self.done}/{self.total}] {note}" if note else f"[{self.done}/{self.total}]"
            self.stream.write(text + "\n")
            self.stream.flush()

    def message(self, text: str) -> None:
        """Print a full line (a failure, say) without breaking the bar."""
        if self.mode == "off":
            return
        if self.mode == "bar" and self._drawn:
            self.stream.write("\r\033[K")
        self.stream.write(text.rstrip("\n") + "\n")
        if self.mode == "bar":
            self._draw("")
        self.stream.flush()

    def clear_line(self) -> None:
        """Erase a drawn bar so that someone else can write a line; the next update redraws it."""
        if self.mode == "bar" and self._drawn:
            self.stream.write("\r\033[K")
            self.stream.flush()
            self._drawn = False

    def close(self) -> None:
        """Finish the bar line (a newline), so later output starts on a fresh line."""
        if self.mode == "bar" and self._drawn:
            self.stream.write("\n")
            self.stream.flush()
            self._drawn = False

    def __enter__(self) -> "ProgressBar":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
