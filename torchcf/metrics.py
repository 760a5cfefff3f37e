"""``torchcf.metrics``, kept where users import it: see
:mod:`torchcf.evaluation.metrics`."""

from .evaluation.metrics import *  # noqa: F403
from .evaluation.metrics import __all__  # noqa: F401
