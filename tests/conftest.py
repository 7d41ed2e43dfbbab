"""Test configuration: float64 for digit checks, no silent rank promotion, fixed seeds."""

import os
import sys

import jax
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

# jaxrefl's caches (compiled programs, form factors: `jaxrefl.compile_cache`) go to a folder
# of this session, shared with the CLI subprocesses it starts, never to the user's home.
import tempfile  # noqa: E402

os.environ.setdefault("JAXREFL_CACHE", tempfile.mkdtemp(prefix="jaxrefl-test-cache-"))

# ... and JAX's persistent compilation cache on from the start, as the CLI turns it on: a program
# compiled here (the in-process CLI runs of tests/test_cli.py, float32 as the command line) is
# loaded, not compiled again, by a subprocess that runs the same (the README's walkthrough), and
# the other way round.
from jaxrefl import compile_cache  # noqa: E402

compile_cache.enable()

# Tests import data_synth from the source tree whether or not the package is installed.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# Property tests draw the same examples on every run (CI must be deterministic).
from hypothesis import settings  # noqa: E402

settings.register_profile("jaxrefl", derandomize=True, deadline=None)
settings.load_profile("jaxrefl")


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Each test module's compiled programs are dropped after it: a process that keeps every
    program of the whole suite grows by gigabytes. A later module that needs one again loads it
    from the persistent compilation cache above."""
    yield
    jax.clear_caches()
