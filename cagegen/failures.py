"""Failures the backends share (raised inside one backend, caught by another's recovery)."""

from __future__ import annotations

from .errors import NestmgError

__all__ = ["PairFailure"]


class PairFailure(NestmgError):
    """One pair (a cage nesting a fine surface) failed in the flow, the re-inflation or the certification.

    Raised by :func:`cagegen.nested.nest_pair`; the ``nested`` backend's recovery and the ``skeleton``
    backend's final inflation catch it. Under the root :class:`NestmgError`, but not a
    :class:`cagegen.CageError`: that is raised when no recovery helps.

    Attributes
    ----------
    stage : str
        ``"flow"``, ``"reinflate"``, ...
    reason : str
        Human readable explanation.
    info : dict
        The pair's figures so far.
    """

    def __init__(self, stage: str, reason: str, info: dict):
        super().__init__(f"{stage}: {reason}")
        self.stage, self.reason, self.info = stage, reason, info
