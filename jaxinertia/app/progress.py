"""Progress bars on a terminal, one line per stage elsewhere.

The library draws its progress with tqdm (training epochs, simulated samples, collected
samples). On a terminal that is a live bar; written to a file (``make demo > log``, a CI
log) each redraw would be another ``\\r``-separated copy of the bar. :func:`configure`
(called by the command line) makes every bar whose output is not a terminal silent while
it runs and print one line when it ends (``torque models: 300/300 in 00:12 (24.5epoch/s)``).
"""

from __future__ import annotations

__all__ = ["configure"]

_installed = False


def _is_terminal(fp) -> bool:
    try:
        return bool(fp.isatty())
    except (AttributeError, ValueError):  # a closed or unusual stream: no live bar
        return False


def configure() -> None:
    """Bars that write to a terminal stay bars; the others end in one line. Idempotent."""
    global _installed
    if _installed:
        return
    from tqdm import std  # tqdm loads in ~50 ms; only a command that runs needs it

    live = std.tqdm.display

    def display(self, msg=None, pos=None):
        if _is_terminal(self.fp):
            return live(self, msg=msg, pos=pos)
        if not self.disable or msg is not None:
            return False  # a redraw (or a bar cleared at its end): nothing in a log
        # The bar is closing (tqdm sets ``disable`` first) and is kept: its one line;
        # tqdm's close() writes the newline.
        d = self.format_dict
        line = self.format_meter(**{**d, "bar_format": "{n_fmt}" + (
            "/{total_fmt}" if d.get("total") else "") + " in {elapsed} ({rate_fmt})"})
        self.fp.write((f"{self.desc}: " if self.desc else "") + line)
        return True

    std.tqdm.display = display
    _installed = True
