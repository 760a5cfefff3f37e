"""The learned particle set and its readable forms.

* :mod:`torchcf.posterior.learned_set`: :class:`Posterior`, ``posterior.pt`` as
  the trainer writes it (format, loading, atomic saving).
* :mod:`torchcf.posterior.tables`: the calibrated parameters as a CSV (one row
  per accepted particle) and a Markdown table per model (median and 5-95 %
  range, with units); the hybrid's shares per group of training pairs (a
  column of the data's ``index.csv`` or a mapping file), with bootstrap
  intervals.
* ``torchcf posterior RUN`` (:mod:`torchcf.cli.posterior`): the
  tables from an existing run (``--by COLUMN`` / ``--groups FILE``: the shares
  per group).
"""

from torchcf.posterior.learned_set import FORMAT, ModelParticles, Posterior

__all__ = ["FORMAT", "ModelParticles", "Posterior"]
