"""Multi-Depth-Map Raytracing (Arikan, Preiner, Wimmer, TVCG 2016): the method."""

from dmrt.camera import Camera
from dmrt.errors import InputError

__version__ = "0.1.0"
__all__ = ["Camera", "InputError", "__version__"]
