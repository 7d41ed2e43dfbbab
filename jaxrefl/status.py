"""How each point's reflectance was determined: the `Status` codes of `Estimate.status`.

Kept free of JAX so that pictures (`jaxrefl.outputs.render`) and files (`jaxrefl.result`,
`jaxrefl.outputs.export`) can name the codes without importing the estimators.
"""

from __future__ import annotations

import enum

__all__ = ["Status", "STATUS_NAMES"]


class Status(enum.IntEnum):
    """Status of a point's estimate; `Estimate.status` holds these codes as int8."""

    MEASURED = 0  # its own samples pin its lobe (with the prior: at least the prior's precision)
    INTERPOLATED = 1  # gated rules: lobe from the window; or, with no own sample, pd from the window
    UNRESOLVED = 2  # nothing pins the lobe: copied from the nearest known lobes (or 0); std infinite
    POOLED = 3  # the shared prior dominates the point's own samples; finite std from the posterior


STATUS_NAMES = tuple(s.name.lower() for s in Status)  # by code: "measured", "interpolated", ...
