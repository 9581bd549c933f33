"""The one progress bar of mbavo: tqdm on stderr, shown only on a terminal."""

from __future__ import annotations

import sys

__all__ = ["bar"]


def bar(total: int, desc: str, enabled: bool = True, unit: str = "frame"):
    """A tqdm bar over ``total`` steps with elapsed time, ETA and steps per second; silent when not
    ``enabled`` or when stderr is not a terminal. ``set_postfix(status=..., keyframes=..., dropped=...)``
    adds fields; use it as a context manager or call ``close()``."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, dynamic_ncols=True,
                disable=not enabled or not sys.stderr.isatty())
