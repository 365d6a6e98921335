"""A small progress bar on stderr, without dependencies.

Used by :func:`cifilter.montecarlo.run` and the reproductions. The bar is one line,
rewritten in place (``\\r``), at most ten times a second::

    weng model 2  [##########----------]  5000/10000 runs  12.1 s, ~12 s left

Whether it is shown follows ``enabled``: ``True`` always, ``False`` never, ``None``
(automatic) only when the stream is a terminal and the work has already taken longer
than ``delay`` seconds, so quick studies and redirected output stay clean.
"""

import sys
import time

__all__ = []

BAR_WIDTH = 20
REFRESH_SECONDS = 0.1
AUTO_DELAY_SECONDS = 2.0


def _is_terminal(stream):
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


def _seconds(value):
    if value < 60:
        return f"{value:.1f} s"
    minutes, seconds = divmod(round(value), 60)
    return f"{minutes} min {seconds:02d} s"


class ProgressBar:
    """Progress of ``total`` units of work, drawn on one line of ``stream``.

    Parameters
    ----------
    total : int
        Units of work (e.g. Monte Carlo runs), >= 1.
    label : str, optional
        Text in front of the bar.
    unit : str, optional
        Name of a unit, printed after the count.
    enabled : bool or None, optional
        ``True`` always draws, ``False`` never, ``None`` draws only on a terminal once
        ``delay`` seconds have passed.
    stream : file-like, optional
        Default: ``sys.stderr`` at the time the bar is made.
    delay : float, optional
        Seconds before an automatic bar first appears.
    """

    def __init__(self, total, label="", unit="runs", enabled=None, stream=None,
                 delay=AUTO_DELAY_SECONDS):
        self.total = max(int(total), 1)
        self.label = label
        self.unit = unit
        self.stream = sys.stderr if stream is None else stream
        if enabled is None:
            self.enabled = _is_terminal(self.stream)
            self.delay = delay
        else:
            self.enabled = bool(enabled)
            self.delay = 0.0
        self.done = 0
        self.start = time.perf_counter()
        self._last_draw = None
        self._drawn = False
        self._drawn_done = None  # the count shown by the last drawing

    def update(self, amount=1):
        """Add ``amount`` finished units and redraw if it is time to."""
        self.done = min(self.done + amount, self.total)
        self._draw(force=self.done >= self.total)

    def close(self):
        """Draw the final state and end the line (only if the bar was shown)."""
        if self._drawn:
            if self._drawn_done != self.done:
                self._draw(force=True)
            self.stream.write("\n")
            self.stream.flush()
            self._drawn = False
        self.enabled = False

    def __enter__(self):
        return self

    def __exit__(self, *exc_info):
        self.close()
        return False

    def _draw(self, force=False):
        if not self.enabled:
            return
        now = time.perf_counter()
        elapsed = now - self.start
        if not self._drawn and elapsed < self.delay:
            return
        if (not force and self._last_draw is not None
                and now - self._last_draw < REFRESH_SECONDS):
            return
        self._last_draw = now
        fraction = self.done / self.total
        filled = round(BAR_WIDTH * fraction)
        bar = "#" * filled + "-" * (BAR_WIDTH - filled)
        text = f"{self.done}/{self.total} {self.unit}  {_seconds(elapsed)}"
        if 0 < self.done < self.total:
            text += f", ~{_seconds(elapsed * (self.total - self.done) / self.done)} left"
        label = f"{self.label}  " if self.label else ""
        self.stream.write(f"\r{label}[{bar}]  {text}\033[K" if _is_terminal(self.stream)
                          else f"\r{label}[{bar}]  {text}")
        self.stream.flush()
        self._drawn, self._drawn_done = True, self.done
