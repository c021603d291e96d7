"""Last-resort cages of the ``nested`` backend: ``FALLBACKS[name](Vf, Ff, m, exc, rep, log, k, gap)``.

When the flow and the intermediate layers fail, ``nested_backend(..., fallback=name)`` builds the layer
with another construction, certified like every other layer: ``"sdf"`` (default, MIT:
:func:`cagegen.sdf.sdf_cage_layer`) or ``"lazy"`` (GPL ``gpytoolbox.copyleft``, loaded only when named:
:func:`cagegen.copyleft.lazy.lazy_cage_layer`). Shared here, at the cagegen level, so that no backend
imports another backend's private code.

Every entry takes the fine layer ``(Vf, Ff)`` in the input's unit-diagonal coordinates, the target ``m``
faces, the flow's error ``exc``, a reporter (``rep.say(message)``), the recovery log, the layer number
and the clearance ``gap`` (absolute in that frame, so relative to the input's diagonal), and returns
``(C, G, layer_info)`` with ``layer_info["fallback"]`` naming it.
"""

from __future__ import annotations

from .errors import CageError

__all__ = ["FALLBACKS", "lazy_fallback", "sdf_fallback"]


def lazy_fallback(Vf, Ff, m, exc, rep, log, k, gap):
    """Fallback ``"lazy"``: a lazy cage (GPL ``gpytoolbox.copyleft``, loaded only here) pushed out to ``gap``.
    """
    try:
        from .copyleft.lazy import lazy_cage_layer
    except ImportError as imp:  # BackendUnavailableError: the GPL extra is not installed
        raise CageError(f"{exc} (lazy fallback unavailable: {imp})", layer=k, reason=exc.reason) from exc
    from .nested.backend import push_out

    rep.say(f"layer {k}: flow and intermediate layers failed; falling back to a lazy cage")
    try:
        C, G, info = lazy_cage_layer(Vf, Ff, m)
    except CageError as exc2:
        raise CageError(f"{exc}; the lazy fallback failed too: {exc2}", layer=k, reason=exc.reason) from exc2
    pinfo = None
    if gap > 0:  # a lazy cage is loose, but may come closer than the clearance somewhere
        C2, pinfo = push_out(C, G, Vf, Ff, gap)
        if C2 is None:
            raise CageError(f"{exc}; the lazy fallback's cage could not keep the clearance {gap:.3g}: "
                            f"{pinfo['reason']}", layer=k, reason=exc.reason)
        C = C2
    log.append({"layer": k, "action": f"fall back to a lazy cage of {len(G)} faces (cagegen.copyleft.lazy)",
                "stage": "fallback", "reason": str(exc)})
    return C, G, {"fallback": "lazy", "lazy": info, "clearance": pinfo, "seconds": {"lazy": info["seconds"]}}


def sdf_fallback(Vf, Ff, m, exc, rep, log, k, gap=0.0):
    """Fallback ``"sdf"``: an sdf cage with ``m`` faces (rounded up to even) keeping and certifying ``gap``
    (``unit=1``: the frame's diagonal). MIT, no copyleft import."""
    from .sdf import sdf_cage_layer

    m = int(m) + int(m) % 2
    rep.say(f"layer {k}: flow and intermediate layers failed; falling back to an sdf cage")
    try:
        # audited input or a certified layer; lengths relative to the input's diagonal (1 here)
        C, G, info = sdf_cage_layer(Vf, Ff, m, check_input=False, unit=1.0, min_gap=float(gap))
    except (CageError, ValueError) as exc2:
        raise CageError(f"{exc}; the sdf fallback failed too: {exc2}", layer=k, reason=exc.reason) from exc2
    log.append({"layer": k, "action": f"fall back to an sdf cage of {len(G)} faces (cagegen.sdf)",
                "stage": "fallback", "reason": str(exc)})
    return C, G, {"fallback": "sdf", "sdf": info, "seconds": {"sdf": info["seconds"]["total"]}}


#: Fallback name -> ``f(Vf, Ff, m, exc, rep, log, k, gap) -> (C, G, layer_info)``. ``nested_backend``'s
#: default is ``"sdf"`` (MIT); ``"lazy"`` (GPL) only by name.
FALLBACKS = {"lazy": lazy_fallback, "sdf": sdf_fallback}
