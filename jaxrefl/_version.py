"""The installed version of jaxrefl (`0.0.0+local` in a source tree that is not installed)."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("jaxrefl")
except PackageNotFoundError:
    __version__ = "0.0.0+local"
