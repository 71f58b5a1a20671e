"""Moved to :mod:`geonav.convergence` (a core metric both policy and experiments use)."""

from geonav.convergence import *  # noqa: F401,F403
from geonav.convergence import (  # noqa: F401
    ConvergenceCriterion,
    ConvergenceResult,
    area_under_curve,
    episodes_to_convergence,
    moving_success_rate,
    summarize,
)
