"""Logging and timing shared by the stage CLIs: every stage logs what it did and how long."""

from __future__ import annotations

import contextlib
import logging
import resource
import sys
import time
from typing import Iterator

__all__ = ["setup_logging", "timed", "peak_rss_mb", "progress"]


def setup_logging(verbose: int = 0, quiet: bool = False) -> None:
    """Configure the root logger for a CLI: INFO by default, DEBUG with -v, WARNING with -q."""
    level = logging.WARNING if quiet else (logging.DEBUG if verbose else logging.INFO)
    logging.basicConfig(
        level=level,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
        stream=sys.stderr,
        force=True,
    )


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, in MiB (Linux ru_maxrss is KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


@contextlib.contextmanager
def timed(what: str, logger: logging.Logger, record: dict | None = None) -> Iterator[None]:
    """Log the wall time of a block; store it in ``record[what]`` (seconds) if given. A block
    that raises logs "failed after", never "done"."""
    t0 = time.perf_counter()
    logger.info("%s ...", what)
    try:
        yield
    except BaseException:
        logger.info("%s failed after %.2f s", what, time.perf_counter() - t0)
        raise
    dt = time.perf_counter() - t0
    if record is not None:
        record[what] = dt
    logger.info("%s done in %.2f s", what, dt)


def progress(iterable, total: int | None = None, desc: str = "", disable: bool | None = None):
    """A tqdm progress bar on stderr (disabled when stderr is not a terminal unless forced)."""
    from tqdm.auto import tqdm

    if disable is None:
        disable = not sys.stderr.isatty()
    return tqdm(iterable, total=total, desc=desc, disable=disable, dynamic_ncols=True)
