"""Watch the map grow in a browser, keep recordings, and view saved maps (optional extra ``[viewer]``).

The live view is served by `viser <https://viser.studio>`_ from the machine that maps (the
vehicle) to any browser that reaches it (the operator's laptop): ``gpumap demo --view``,
``gpumap replay --view`` (``--view-host``/``--view-port``, 127.0.0.1:8080 by default),
``gpumap view MAP.npz`` or ``gpumap view RUN.gpumap-rec``. Recordings (``--record FILE``,
:mod:`gpumap.viewer.recording`) need only NumPy, so a vehicle can record without the
viewer installed.

viser is imported lazily: without it, :func:`require_viser` raises an ``ImportError`` saying
``pip install 'gpumap[viewer]'``.
"""

from __future__ import annotations

from typing import Any

from gpumap.viewer.recording import MapRecording, Recorder, read_recording

__all__ = ["MISSING_VIEWER", "MapRecording", "Recorder", "read_recording", "require_viser"]

MISSING_VIEWER = "the live view needs the optional viewer dependencies (viser): pip install 'gpumap[viewer]'"


def require_viser() -> Any:
    """Import and return :mod:`viser`, or raise ``ImportError`` saying how to install it."""
    try:
        import viser
    except ImportError as e:
        raise ImportError(f"{MISSING_VIEWER} ({e})") from None
    return viser
