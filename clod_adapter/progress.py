"""Progress for long work: a tqdm bar on a terminal, one plain tqdm line every 10 % in a log
(:func:`progress_bar`; :class:`LineProgress` is tqdm with that line form: no carriage returns,
postfix changes do not print)."""
from __future__ import annotations

import math
import sys

from tqdm import tqdm

__all__ = ["LineProgress", "progress_bar"]

#: the log line: ``desc: n/total unit (pct %), elapsed s, left s; postfix``.
LINE_FORMAT = "{desc}: {n_fmt}/{total_fmt} {unit} ({percentage:.0f} %), {elapsed_s:.0f} s, {remaining_s:.0f} s left{postfix}"


class _Lines:
    """The stream tqdm writes to: each status it writes (``\\r`` + text) becomes one line."""

    def __init__(self, stream) -> None:
        self.stream = stream

    def write(self, s: str) -> None:
        s = s.replace("\r", "").replace("\x1b[A", "").rstrip()  # no cursor moves in a log
        if s:
            self.stream.write(s + "\n")

    def flush(self) -> None:
        self.stream.flush()


class LineProgress(tqdm):
    """tqdm for logs that are not a terminal: one line each ``miniters`` steps and one at the
    end (each count printed once), the postfix shown on the next line rather than printed."""

    def __init__(self, *args, **kw) -> None:
        self._shown = kw.get("initial", 0)
        super().__init__(*args, **kw)

    def set_postfix(self, ordered_dict=None, refresh: bool = True, **kw) -> None:
        super().set_postfix(ordered_dict, refresh=False, **kw)

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        super().set_postfix_str(s, refresh=False)

    def display(self, msg=None, pos=None):
        if self.n == self._shown:
            return True
        self._shown = self.n
        return super().display(msg, pos)


def progress_bar(total: int, desc: str, *, unit: str = "it", disable: bool = False, initial: int = 0,
                 leave: bool = True, file=None, every: float = 0.1) -> tqdm:
    """A tqdm bar when ``file`` (default stderr) is a terminal, else :class:`LineProgress` (a plain
    line each ``every`` of the total, 10 % by default, :data:`LINE_FORMAT`); ``disable``:
    neither (a silent tqdm)."""
    stream = file or sys.stderr
    if disable:
        return tqdm(total=total, disable=True)
    isatty = getattr(stream, "isatty", None)
    if isatty is not None and isatty():
        return tqdm(total=total, initial=initial, desc=desc, unit=unit, leave=leave, file=stream,
                    dynamic_ncols=True)
    step = max(1, int(math.ceil(every * total))) if total > 0 else 1
    # maxinterval inf: tqdm's monitor thread otherwise sets miniters to 1 once a bar has not
    # printed for 10 s, and every step became a line (clod-eval's 5,000-step ceiling: 5,000
    # lines); position 0: a bar opened inside another one moves no cursor in a log
    return LineProgress(total=total, initial=initial, desc=desc, unit=unit, leave=True, file=_Lines(stream),
                        miniters=step, mininterval=0.0, maxinterval=float("inf"), position=0,
                        bar_format=LINE_FORMAT)
