"""The learned hybrid in Eclipse SUMO: export, co-simulation, verification.

- :mod:`torchcf.sumo.backend`: the optional packages (``pip install
  'torchcf[sumo]'``), SUMO's binaries, one libsumo simulation at a time;
- :mod:`torchcf.sumo.export`: the hybrid's particles of the models SUMO has (IDM)
  as a ``vTypeDistribution``, with the exact parameter mapping;
- :mod:`torchcf.sumo.cosim`: :class:`CoSimulation`, SUMO vehicles driven by a
  :class:`~torchcf.traffic.HybridSampler` every step (every model and effect);
- :mod:`torchcf.sumo.network`, :mod:`torchcf.sumo.fcd`: straight test roads;
  SUMO's floating car data read back;
- :mod:`torchcf.sumo.verify`: the test split replayed in SUMO and scored with
  torchcf's metrics beside torchcf's own rollout;
- ``torchcf sumo export|verify RUN``: the command (:mod:`torchcf.cli.sumo`).

Importing this package imports no SUMO module; the first use does.
"""

from .backend import INSTALL_HINT, SumoError, SumoMissingError
from .cosim import CoSimulation, Perceived
from .export import Export, export_hybrid, idm_vtype, write_export
from .fcd import Fcd, read_fcd
from .network import straight_edges
from .verify import Replay, replay, score_cells, verify_run

__all__ = [
    "INSTALL_HINT",
    "CoSimulation",
    "Export",
    "Fcd",
    "Perceived",
    "Replay",
    "SumoError",
    "SumoMissingError",
    "export_hybrid",
    "idm_vtype",
    "read_fcd",
    "replay",
    "score_cells",
    "straight_edges",
    "verify_run",
    "write_export",
]
