"""torchconn: discrete connections on cell complexes in PyTorch."""
from . import so3, tolerances, transport

__version__ = "0.1.0"

__all__ = ["so3", "tolerances", "transport", "__version__"]
