"""gsfix-online: online TSDF + 3D Gaussian Splatting mapping with GSFixer diffusion repair.

Data flow (one package per stage): ``sources`` (readers, logs, replay) -> ``mapping`` (TSDF, splats)
-> ``keyframes`` -> ``fixer`` (GSFixer) -> ``repair`` -> ``inspection``; ``runtime`` wires them to
ZeroMQ. Importing the package is cheap: heavy libraries load inside the components that use them.
"""

from typing import TYPE_CHECKING, Any

from gsfix_online.types import FrameError, Intrinsics, RGBDFrame, make_frame

if TYPE_CHECKING:
    from gsfix_online.inspection.client import MapClient

__version__ = "0.1.0"
__all__ = ["FrameError", "Intrinsics", "MapClient", "RGBDFrame", "make_frame", "__version__"]


def __getattr__(name: str) -> Any:
    if name == "MapClient":  # the map server's client loads pyzmq only when asked for
        from gsfix_online.inspection.client import MapClient

        return MapClient
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
