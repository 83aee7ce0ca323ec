"""Logging and progress bars, set up once by the command line.

Library code logs through ``logging.getLogger(__name__)`` and wraps long loops in
``progress(...)``; the CLI decides verbosity. Progress bars go to stderr and stay
quiet when stderr is not a terminal unless ``CRISTAL_PROGRESS=1``.
"""

from __future__ import annotations

import logging
import os
import sys
from typing import Iterable, Iterator, TypeVar

T = TypeVar("T")

__all__ = ["setup_logging", "progress"]


def setup_logging(verbosity: int = 0) -> None:
    level = logging.WARNING if verbosity < 0 else logging.INFO if verbosity == 0 else logging.DEBUG
    try:
        from rich.logging import RichHandler

        handler: logging.Handler = RichHandler(show_path=verbosity > 0, rich_tracebacks=False, markup=False)
        fmt = "%(message)s"
    except ImportError:  # pragma: no cover
        handler = logging.StreamHandler(sys.stderr)
        fmt = "%(asctime)s %(levelname)s %(name)s: %(message)s"
    logging.basicConfig(level=level, format=fmt, datefmt="[%X]", handlers=[handler], force=True)
    logging.getLogger("numba").setLevel(logging.WARNING)
    logging.getLogger("matplotlib").setLevel(logging.WARNING)
    logging.getLogger("PIL").setLevel(logging.WARNING)


def _enabled() -> bool:
    env = os.environ.get("CRISTAL_PROGRESS")
    if env is not None:
        return env not in ("0", "", "false")
    return sys.stderr.isatty()


def progress(it: Iterable[T], desc: str, total: int | None = None, unit: str = "it") -> Iterator[T]:
    """A tqdm progress bar on stderr (silent when not interactive)."""
    from tqdm import tqdm

    yield from tqdm(it, desc=desc, total=total, unit=unit, disable=not _enabled(), dynamic_ncols=True, leave=False)
