"""Test configuration: float64 for digit checks, no silent rank promotion, fixed seeds."""

import os
import sys

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

# Tests import data_synth from the source tree whether or not the package is installed.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# Property tests draw the same examples on every run (CI must be deterministic).
from hypothesis import settings  # noqa: E402

settings.register_profile("jaxrefl", derandomize=True, deadline=None)
settings.load_profile("jaxrefl")
