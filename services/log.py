"""Logging and progress bars, set up once by the command line.

Library code logs through ``logging.getLogger(__name__)`` and wraps long loops in
``progress(...)``; the CLI decides verbosity. Logs and progress bars go to stderr (stdout
is for a command's summary, ending with its JSON line); progress bars stay quiet when
stderr is not a terminal unless ``CRISTAL_PROGRESS=1``.
"""

from __future__ import annotations

import logging
import os
import sys
from typing import Iterable, Iterator, TypeVar

T = TypeVar("T")

__all__ = ["setup_logging", "progress"]


class _StderrHandler(logging.StreamHandler):
    """A StreamHandler on whatever ``sys.stderr`` is at emit time (pytest and tools swap it)."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self):  # type: ignore[override]
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


def setup_logging(verbosity: int = 0) -> None:
    """Log to **stderr**, never stdout: a command's stdout is its human summary lines and, last, one JSON line.

    On a terminal: rich's handler (colours, aligned columns). Otherwise (pipes, files, services under
    systemd/Kubernetes): one plain line per record, never wrapped, so the server's JSON event lines
    stay one line each and remain greppable.
    """
    level = logging.WARNING if verbosity < 0 else logging.INFO if verbosity == 0 else logging.DEBUG
    handler: logging.Handler | None = None
    fmt, datefmt = "%(asctime)s %(levelname)s %(name)s: %(message)s", None
    if sys.stderr.isatty():
        try:
            from rich.console import Console
            from rich.logging import RichHandler

            handler = RichHandler(console=Console(stderr=True), show_path=verbosity > 0, rich_tracebacks=False,
                                  markup=False)
            fmt, datefmt = "%(message)s", "[%X]"
        except ImportError:  # pragma: no cover
            handler = None
    if handler is None:
        handler = _StderrHandler()
    logging.basicConfig(level=level, format=fmt, datefmt=datefmt, handlers=[handler], force=True)
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


def progress_bar(desc: str, total: int | None = None, unit: str = "it"):
    """The same bar, advanced by hand (``with progress_bar(...) as bar: bar.update(k)``)."""
    from tqdm import tqdm

    return tqdm(desc=desc, total=total, unit=unit, disable=not _enabled(), dynamic_ncols=True, leave=False)
