"""Progress for long work: a tqdm bar on a terminal, one plain line every 10 % in a log
(:func:`progress_bar`; :class:`LineProgress` is that line form, no carriage returns)."""
from __future__ import annotations

import math
import sys
import time

__all__ = ["LineProgress", "progress_bar"]


class LineProgress:
    """tqdm's small interface (``update``, ``set_postfix``, ``set_postfix_str``, ``close``) for
    logs that are not a terminal: one plain line every ``every`` of the total (and at the end),
    no carriage returns."""

    def __init__(self, total: int, desc: str, unit: str = "it", initial: int = 0, every: float = 0.1,
                 file=None) -> None:
        self.total, self.desc, self.unit, self.n = int(total), desc, unit, int(initial)
        self.file = file
        self.every = every
        self.postfix = ""
        self.t0 = time.perf_counter()
        self.n0 = self.n
        self._next = self._threshold_after(self.n)
        self.closed = False

    def _threshold_after(self, n: int) -> int:
        if self.total <= 0:
            return 1 << 62
        step = max(1, int(math.ceil(self.every * self.total)))
        return min(self.total, (n // step + 1) * step)

    def set_postfix(self, ordered_dict=None, refresh: bool = True, **kw) -> None:
        items = dict(ordered_dict or {}, **kw)
        self.postfix = ", ".join(f"{k}={v}" for k, v in items.items())

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        self.postfix = str(s)

    def update(self, n: int = 1) -> None:
        self.n += n
        if self.n >= self._next:
            self._line()
            self._next = self._threshold_after(self.n)

    def _line(self) -> None:
        el = time.perf_counter() - self.t0
        done = self.n - self.n0
        left = (self.total - self.n) * el / done if done > 0 else float("nan")
        pct = 100.0 * self.n / self.total if self.total else 100.0
        tail = f"; {self.postfix}" if self.postfix else ""
        eta = f", {left:.0f} s left" if left == left else ""
        print(f"{self.desc}: {self.n}/{self.total} {self.unit} ({pct:.0f} %), {el:.0f} s{eta}{tail}",
              file=self.file or sys.stderr, flush=True)

    def close(self) -> None:
        self.closed = True

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def progress_bar(total: int, desc: str, *, unit: str = "it", disable: bool = False, initial: int = 0,
                 leave: bool = True, file=None, every: float = 0.1):
    """A tqdm bar when ``file`` (default stderr) is a terminal, else :class:`LineProgress` (a plain
    line every 10 %); ``disable``: neither (a silent tqdm)."""
    from tqdm import tqdm

    stream = file or sys.stderr
    if disable:
        return tqdm(total=total, disable=True)
    isatty = getattr(stream, "isatty", None)
    if isatty is not None and isatty():
        return tqdm(total=total, initial=initial, desc=desc, unit=unit, leave=leave, file=stream,
                    dynamic_ncols=True)
    return LineProgress(total, desc, unit=unit, initial=initial, every=every, file=stream)
