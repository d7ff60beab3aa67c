"""hgca_core: headless hGCA (hierarchical Generative Cellular Automata) for LiDAR scene extrapolation."""
from hgca_core.errors import HgcaError, InputError

__version__ = "0.1.0"

__all__ = ["HgcaError", "InputError", "__version__"]
