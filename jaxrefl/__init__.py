"""jaxrefl: dense surface reflectance by inverse rendering, with JAX and Embree.

`estimate(scan, method=Local() | Radiosity() | Photon() | Auto(), *, holdout=None)`
returns an `Estimate` (per-point pd, ps, roughness, their standard deviations and a
`Status` per point) with `.save()`, `.relight()`, `.to_ply()` and `.figure()`.
"""

from importlib import import_module as _import_module

from . import geometry as geometry  # the layers (sub-packages)
from . import methods as methods
from . import outputs as outputs
from . import reflectance as reflectance
from . import result as result
from . import scan as scan
from ._version import __version__ as __version__
from .api import Auto as Auto
from .api import Local as Local
from .api import Photon as Photon
from .api import Radiosity as Radiosity
from .api import estimate as estimate
from .result import Estimate as Estimate
from .result import load_result as load_result
from .result import save_result as save_result
from .scan.io import Scan as Scan
from .scan.io import ScanError as ScanError
from .scan.io import load_scan as load_scan
from .scan.io import save_scan as save_scan
from .status import Status as Status

__all__ = ["estimate", "Local", "Radiosity", "Photon", "Auto", "Estimate", "Status", "Scan", "ScanError",
           "load_scan", "save_scan", "load_result", "save_result"]

# Every module of the layers above resolves after `import jaxrefl` (`jaxrefl.scan.ingest`, ...);
# `capture` (pyserial), `paper` (data_synth), `cli` and `batch` load on use.
for _name in ("outputs.export", "scan.ingest", "scan.preprocess"):
    _import_module(f"{__name__}.{_name}")
