"""gsfix-online: online TSDF + 3D Gaussian Splatting mapping with GSFixer diffusion repair.

Data flow (one package per stage): ``sources`` (readers, logs, replay) -> ``mapping`` (TSDF, splats)
-> ``keyframes`` -> ``fixer`` (GSFixer) -> ``repair`` -> ``inspection``; ``runtime`` wires them to
ZeroMQ. Importing the package is cheap: heavy libraries load inside the components that use them.
"""

from gsfix_online.types import FrameError, Intrinsics, RGBDFrame, make_frame

__version__ = "0.1.0"
__all__ = ["FrameError", "Intrinsics", "RGBDFrame", "make_frame", "__version__"]
