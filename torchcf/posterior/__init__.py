"""The learned particle set and its readable forms.

* :mod:`torchcf.posterior.learned_set`: :class:`Posterior`, ``posterior.pt`` as
  the trainer writes it (format, loading, atomic saving).
* :mod:`torchcf.posterior.tables`: the calibrated parameters as a CSV (one row
  per accepted particle) and a Markdown table per model (median and 5-95 %
  range, with units).
* ``python -m torchcf.posterior RUN`` (:mod:`torchcf.posterior.__main__`): both,
  from an existing run.
"""

from torchcf.posterior.learned_set import FORMAT, ModelParticles, Posterior

__all__ = ["FORMAT", "ModelParticles", "Posterior"]
