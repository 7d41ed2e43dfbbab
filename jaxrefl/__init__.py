"""jaxrefl: dense surface reflectance by inverse rendering, with JAX and Embree.

`estimate(scan, method=Local() | Radiosity() | Photon() | Auto(), *, holdout=None)`
returns an `Estimate` (per-point pd, ps, roughness, their standard deviations and a
`Status` per point) with `.save()`, `.relight()`, `.to_ply()` and `.figure()`.
"""

from importlib.metadata import PackageNotFoundError, version

from . import brdf as brdf, io as io, raycast as raycast, rig as rig
from . import classify as classify, lights as lights, local as local, preprocess as preprocess
from . import render as render, result as result
from . import export as export, ingest as ingest, relight as relight
from .api import Auto as Auto, Local as Local, Photon as Photon, Radiosity as Radiosity, estimate as estimate
from .io import Scan as Scan, ScanError as ScanError, load_scan as load_scan, save_scan as save_scan
from .local import Estimate as Estimate
from .result import load_result as load_result, save_result as save_result
from .status import Status as Status

__all__ = ["estimate", "Local", "Radiosity", "Photon", "Auto", "Estimate", "Status", "Scan", "ScanError",
           "load_scan", "save_scan", "load_result", "save_result"]

try:
    __version__ = version("jaxrefl")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+local"
