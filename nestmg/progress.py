"""Progress reporting shared by the pipeline stages (rich), silent when disabled or not a terminal."""

from __future__ import annotations

import contextlib
import logging
import sys
import time
from collections.abc import Iterator


class Stage:
    """Handle yielded by :func:`stages`; call ``advance(label)`` after each step."""

    def __init__(self, progress, task):
        self._progress, self._task = progress, task

    def advance(self, label: str | None = None) -> None:
        """Mark one step done; optionally change the displayed label."""
        if self._progress is not None:
            kw = {"description": label} if label else {}
            self._progress.update(self._task, advance=1, **kw)

    def describe(self, label: str) -> None:
        """Change the displayed label without advancing."""
        if self._progress is not None:
            self._progress.update(self._task, description=label)


@contextlib.contextmanager
def stages(total: int, label: str, enabled: bool | None = True) -> Iterator[Stage]:
    """Context manager showing a rich progress bar of ``total`` steps on stderr.

    ``enabled=None`` shows it only when stderr is a terminal.
    """
    if enabled is None:
        enabled = sys.stderr.isatty()
    if not enabled:
        yield Stage(None, None)
        return
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
        console=Console(stderr=True),
        transient=False,
    ) as progress:
        task = progress.add_task(label, total=total)
        yield Stage(progress, task)


class Timer:
    """Accumulate wall times per named stage: ``with timer("tets"): ...``; ``timer.seconds`` dict."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextlib.contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0


#: logger of the pipeline's stage lines (``nestmg``): the CLI prints them when stderr is not a terminal.
#: Its children ``nestmg.vtk`` / ``nestmg.render`` receive third-party messages (:mod:`nestmg.render`);
#: ipctk's go to ``cagegen.ipctk`` (cagegen does not import nestmg). The NullHandler keeps Python's
#: "last resort" handler from printing their warnings on stderr when the application configured no logging.
log = logging.getLogger("nestmg")
log.addHandler(logging.NullHandler())


def log_third_party(logger: logging.Logger, level: int, source: str, msg: str) -> None:
    """Log a third-party library's message as ``"<source>: <msg>"``, marked ``record.third_party``.

    Parameters
    ----------
    logger : logging.Logger
        A child of ``nestmg`` (e.g. ``nestmg.vtk``).
    level : int
        Logging level (``logging.WARNING``, ...).
    source : str
        Library or warning category, e.g. ``"VTK"``.
    msg : str
        The message.
    """
    logger.log(level, "%s: %s", source, msg, extra={"third_party": source})


class _NoThirdParty(logging.Filter):
    """Stage lines only: drop third-party records (marked by :func:`log_third_party`)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not hasattr(record, "third_party")


def stage_line(msg: str, t0: float | None = None) -> None:
    """Log one stage line (``INFO`` on the ``nestmg`` logger), with the elapsed time since ``t0``."""
    if t0 is not None:
        msg = f"{time.perf_counter() - t0:7.1f} s  {msg}"
    log.info(msg)


def enable_stage_lines(stream=None) -> None:
    """Print the pipeline's stage lines (one per stage, flushed) on ``stream`` (default stderr).

    The CLI calls this when stderr is not a terminal, so a long run in a script or a CI log shows where
    it is; in a terminal the rich progress bars do that instead. Third-party messages routed to the
    ``nestmg`` loggers are not printed. Idempotent.
    """
    for h in log.handlers:
        if getattr(h, "_nestmg_stage_lines", False):
            return
    h = logging.StreamHandler(stream if stream is not None else sys.stderr)
    h.setFormatter(logging.Formatter("[nestmg] %(message)s"))
    h.addFilter(_NoThirdParty())
    h._nestmg_stage_lines = True  # type: ignore[attr-defined]
    log.addHandler(h)
    log.setLevel(logging.INFO)
    log.propagate = False
