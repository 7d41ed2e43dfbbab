"""jaxrefl: dense surface reflectance by inverse rendering, with JAX and Embree."""

from importlib.metadata import PackageNotFoundError, version

from . import brdf as brdf, io as io, raycast as raycast, rig as rig
from . import classify as classify, lights as lights, local as local, preprocess as preprocess
from . import render as render, result as result
from . import export as export, ingest as ingest, relight as relight
from .io import Scan as Scan, ScanError as ScanError, load_scan as load_scan, save_scan as save_scan

try:
    __version__ = version("jaxrefl")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+local"
