"""gsfix-online: online TSDF + 3D Gaussian Splatting mapping with GSFixer diffusion repair.

The packages follow the data flow, bottom to top, and import only downward (``lint-imports``
checks it): ``core`` (types, config, geometry, metrics, progress, atomic I/O) -> ``sources``
(readers, logs, replay) -> ``scene`` (procedural scenes) and ``runtime`` (transport, wire
format, graphs) -> ``mapping`` (TSDF, Gaussian map) -> ``fixer`` (GSFixer) -> ``repair`` ->
``services`` (the components the nodes wrap) -> ``jobs`` (repair run, demo, reports,
pretraining, bench, stress) -> ``apps`` (CLI, viewer, map client) -> ``nodes``. Importing the
package is cheap: heavy libraries load inside the components that use them.
"""

from typing import TYPE_CHECKING, Any

from gsfix_online.core.types import FrameError, Intrinsics, RGBDFrame, make_frame

if TYPE_CHECKING:
    from gsfix_online.apps.client import MapClient

__version__ = "0.1.0"
__all__ = ["FrameError", "Intrinsics", "MapClient", "RGBDFrame", "make_frame", "__version__"]


def __getattr__(name: str) -> Any:
    if name == "MapClient":  # the map server's client loads pyzmq only when asked for
        from gsfix_online.apps.client import MapClient

        return MapClient
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
