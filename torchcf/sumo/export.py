"""The hybrid's particles as SUMO vehicle types (``torchcf sumo export``).

SUMO has one of torchcf's eight models natively: the IDM. The others are listed,
never silently dropped:

- OVM, GFM, FVDM, LLCS, HL, MPC: no SUMO car-following model has their equations.
- LLCTG (``ks (s - v tau - l) + kv dv``) is *not* SUMO's ``ACC``/``CACC``: those
  switch between speed control, gap control and gap-closing controllers by gap
  thresholds, with their own gains and a collision-avoidance mode, so no choice of
  their parameters gives LLCTG's linear law everywhere.

**IDM, SPEC section 3 against SUMO's ``MSCFModel_IDM``.** SPEC's command is
``u = a (1 - (v / v0)^delta - (s* / s)^2)``,
``s* = s0 + max(0, v T - v dv / (2 sqrt(a b)))`` with ``s = x_lead - x`` the
front-to-front spacing (no leader length) and ``dv = v_lead - v``. SUMO's IDM
computes the same expression with ``s`` replaced by its *bumper-to-bumper* gap
``g = x_lead - length_lead - x`` and ``s0`` by the follower's ``minGap``; one
step of it is ``v' = max(0, v + u dt / n)`` repeated ``n`` times,
``n = max(1, int(dt / stepping + 0.5))`` internal sub-steps (the gap shrinking by
``(v' - v_lead) dt / n`` between them). The mapping, one ``vType`` per particle:

=====================  ==========================  ================================
SUMO attribute          value                       why
=====================  ==========================  ================================
``carFollowModel``      ``IDM``
``accel``               ``a`` [m/s^2]
``decel``               ``b`` [m/s^2]               enters ``2 sqrt(accel decel)``
``desiredMaxSpeed``     ``v0`` [m/s]                SUMO's IDM desired speed:
                                                    ``min(desiredMaxSpeed,
                                                    speed limit) x speedFactor``
``maxSpeed``            ``max(v0, 55.56)`` [m/s]    the car's top speed (SUMO's
                                                    passenger default)
``speedFactor``         ``1`` (``speedDev`` 0)      so the desired speed is ``v0``
``tau``                 ``T`` [s]
``minGap``              ``s0`` [m]                  SUMO: bumper to bumper
``delta``               ``delta``
``stepping``            ``dt`` [s]                  one internal step: SPEC's
                                                    explicit step
``emergencyDecel``      ``max(b, emergency_decel)``  SUMO's hardest braking; SPEC
                                                    has no bound
``length``              ``length`` [m]              the vehicle (default: the data's
                                                    leader length ``L``)
``probability``         ``1 / P``                   the particle's mass in the
                                                    whole hybrid (``P`` particles)
=====================  ==========================  ================================

With ``--step-method.ballistic true`` (SUMO's global option; an additional file
cannot set it) SUMO moves a vehicle by ``(v + v') dt / 2``, which is SPEC's
``v dt + a dt^2 / 2`` with ``a = (v' - v) / dt``; SUMO's default (semi-implicit
Euler, ``v' dt``) is not. Where the two still differ, measured by
``torchcf sumo verify`` and ``tests/sumo/test_sumo_verify.py``:

- the spacing: SUMO's IDM reads ``g = s - length_lead``, so it equals SPEC's IDM
  only where the leader's length is 0 for its follower (``verify`` places each
  replayed leader one length ahead of its recorded front). In a network of
  vehicles of length ``L`` an exported particle drives as SPEC's IDM would on the
  bumper gap;
- a stop within a step: SPEC moves ``max(v dt + u dt^2 / 2, 0)`` and records ``u``,
  SUMO brakes to ``v' = 0`` over the whole step (``v dt / 2``);
- above the desired speed (``v > v0``, e.g. a follower starting faster than its
  particle's ``v0``) SUMO brakes at ``decel`` towards ``v0``; SPEC's IDM keeps its
  own law, ``a (1 - (v / v0)^delta - ...)`` (milder for ``v`` near ``v0``). This is
  the largest difference on real data: metres of position over a minute in the
  few pairs where it happens (``verify`` reports it apart);
- the floor of the divisor: SPEC 0.1 m, SUMO 0.001 m;
- SUMO never brakes harder than ``emergencyDecel`` (and counts an emergency brake
  when it would);
- SUMO takes the minimum with its free-road speed, IDM at a gap of 1e6 m (the
  same as the followed command up to ``(s* / 1e6)^2``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple
from xml.sax.saxutils import quoteattr

from torch import Tensor

from ..config import TrainConfig, load_split
from ..data import DATASETS
from ..models import get_model
from ..posterior import Posterior
from ..system.files import atomic_write_text, ensure_directory, write_json
from ..system.records import Record
from .backend import SumoError

#: The ``vTypeDistribution`` id of an export.
DISTRIBUTION_ID = "torchcf_hybrid"
#: File names an export writes into its folder.
VTYPES_FILE = "hybrid.vtypes.add.xml"
MANIFEST_FILE = "export.json"
#: SUMO's emergency deceleration of a passenger car [m/s^2], the default bound.
EMERGENCY_DECEL = 9.0
#: SUMO's default top speed of a passenger car [m/s] (200 km/h): ``maxSpeed``.
TOP_SPEED = 55.56
#: Why each model is not exported (the models SUMO has natively are in MAPPINGS).
NOT_IN_SUMO = {
    "ovm": "SUMO has no optimal velocity model",
    "gfm": "SUMO has no generalised force model",
    "fvdm": "SUMO has no full velocity difference model",
    "llctg": "SUMO's ACC/CACC switch controllers by gap; not LLCTG's linear law",
    "llcs": "SUMO has no constant-spacing linear controller",
    "hl": "SUMO has no linear controller with an actuation lag",
    "mpc": "SUMO has no model-predictive controller",
}


def idm_vtype(
    theta: Tensor, *, dt: float, length: float, emergency_decel: float
) -> dict[str, float | str]:
    """SUMO ``vType`` attributes of one IDM particle (module docstring's table).

    Args:
        theta: ``(6,)`` IDM parameters in torchcf's order ``(a, b, v0, T, s0,
            delta)``, SI.
        dt: SUMO's step [s] (the internal ``stepping``: one sub-step).
        length: the vehicle's length [m].
        emergency_decel: SUMO's hardest braking [m/s^2] (at least ``b``).

    Returns:
        attribute -> value, floats at full precision.

    Examples:
        >>> import torch
        >>> from torchcf.sumo import idm_vtype
        >>> theta = torch.tensor([1.5, 2.0, 33.0, 1.2, 2.0, 4.0], dtype=torch.float64)
        >>> vtype = idm_vtype(theta, dt=0.1, length=5.0, emergency_decel=9.0)
        >>> vtype["carFollowModel"], vtype["tau"], vtype["minGap"], vtype["decel"]
        ('IDM', 1.2, 2.0, 2.0)
    """
    a, b, v0, T, s0, delta = (float(x) for x in theta.tolist())
    return {
        "carFollowModel": "IDM",
        "accel": a,
        "decel": b,
        "desiredMaxSpeed": v0,
        "maxSpeed": max(v0, TOP_SPEED),
        "speedFactor": 1.0,
        "speedDev": 0.0,
        "tau": T,
        "minGap": s0,
        "delta": delta,
        "stepping": float(dt),
        "emergencyDecel": max(b, float(emergency_decel)),
        "length": float(length),
    }


#: Models SUMO has natively: name -> the vType attributes of one particle.
MAPPINGS = {"idm": idm_vtype}


@dataclass(frozen=True)
class NotExported(Record):
    """A model of the hybrid SUMO does not have: its particles, their share of
    the hybrid and why (``export.json``'s ``not_exported[model]``)."""

    particles: int
    share: float
    reason: str


@dataclass(frozen=True)
class VTypeOrigin(Record):
    """Where a vType comes from: the model, its row among the model's hybrid
    particles and the training pair it was kept for (``vtypes[id]``)."""

    model: str
    row: int
    pair_id: int


@dataclass(frozen=True)
class ExportManifest(Record):
    """What an export carries: the content of ``export.json``.

    Attributes:
        format: ``"torchcf.sumo.export/1"``.
        dataset: the run's data set.
        distribution: the ``vTypeDistribution``'s id.
        file: the additional file's name.
        particles: the hybrid's particles, all models.
        exported: model -> its particles exported.
        not_exported: model -> its particles left out, and why.
        share: the fraction of the hybrid's particles exported.
        step_length: SUMO's ``--step-length`` [s] (the data's dt).
        step_method: ``"ballistic"``.
        length: the vehicles' length [m].
        emergency_decel: SUMO's hardest braking [m/s^2].
        vtypes: vType id -> where it comes from.
    """

    format: str
    dataset: str
    distribution: str
    file: str
    particles: int
    exported: dict[str, int]
    not_exported: dict[str, NotExported]
    share: float
    step_length: float
    step_method: str
    length: float
    emergency_decel: float
    vtypes: dict[str, VTypeOrigin]

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> ExportManifest:
        """The manifest of ``export.json``'s content."""
        return cls(
            **{
                **raw,
                "exported": dict(raw["exported"]),
                "not_exported": {
                    name: NotExported.from_json(s)
                    for name, s in raw["not_exported"].items()
                },
                "vtypes": {
                    key: VTypeOrigin.from_json(v) for key, v in raw["vtypes"].items()
                },
            }
        )


class Export(NamedTuple):
    """An export: the additional file's text and its manifest.

    Attributes:
        xml: the SUMO additional file (a ``vTypeDistribution``).
        manifest: what it carries (``export.json``): the models exported and
            left out, the share exported, each vType's origin, the settings.

    Examples:
        >>> import torch
        >>> from torchcf.posterior import ModelParticles, Posterior
        >>> def particles(theta):  # one model's particles in the hybrid (SI)
        ...     n = len(theta)
        ...     return ModelParticles(
        ...         ("a", "b", "v0", "T", "s0", "delta")[: len(theta[0])],
        ...         torch.tensor(theta).double(), torch.zeros(n).double(),
        ...         torch.arange(n), torch.arange(n),
        ...     )
        >>> hybrid = {
        ...     "idm": particles([[1.5, 2.0, 33.0, 1.2, 2.0, 4.0]] * 3),
        ...     "ovm": particles([[0.8, 1.5, 30.0, 20.0]]),  # OVM's four parameters
        ... }
        >>> posterior = Posterior(
        ...     "demo", "per_pair", 1, ("idm", "ovm"), {"idm": 0.75, "ovm": 0.25},
        ...     torch.arange(4), hybrid, {"idm": {}, "ovm": {}},
        ... )
        >>> from torchcf.sumo import export_hybrid
        >>> export = export_hybrid(posterior, dt=0.1, length=5.0)  # [s], [m]
        >>> export.xml.count("<vType "), export.manifest.exported
        (3, {'idm': 3})
        >>> export.manifest.not_exported["ovm"].reason
        'SUMO has no optimal velocity model'
    """

    xml: str
    manifest: ExportManifest


def _value(value: float | str) -> str:
    return repr(float(value)) if isinstance(value, float) else str(value)


def export_hybrid(
    posterior: Posterior,
    *,
    dt: float,
    length: float,
    emergency_decel: float = EMERGENCY_DECEL,
) -> Export:
    """The hybrid's particles of the models SUMO has, as vTypes.

    Args:
        posterior: the learned set.
        dt: the step the particles were learned at [s] (SUMO's ``--step-length``).
        length: vehicle length [m].
        emergency_decel: SUMO's hardest braking [m/s^2].

    Returns:
        :class:`Export`.

    Raises:
        SumoError: bad settings, or no particle of a model SUMO has.

    Examples:
        >>> import torch
        >>> from torchcf.posterior import ModelParticles, Posterior
        >>> def particles(theta):  # one model's particles in the hybrid (SI)
        ...     n = len(theta)
        ...     return ModelParticles(
        ...         ("a", "b", "v0", "T", "s0", "delta")[: len(theta[0])],
        ...         torch.tensor(theta).double(), torch.zeros(n).double(),
        ...         torch.arange(n), torch.arange(n),
        ...     )
        >>> hybrid = {
        ...     "idm": particles([[1.5, 2.0, 33.0, 1.2, 2.0, 4.0]] * 3),
        ...     "ovm": particles([[0.8, 1.5, 30.0, 20.0]]),  # OVM's four parameters
        ... }
        >>> posterior = Posterior(
        ...     "demo", "per_pair", 1, ("idm", "ovm"), {"idm": 0.75, "ovm": 0.25},
        ...     torch.arange(4), hybrid, {"idm": {}, "ovm": {}},
        ... )
        >>> from torchcf.sumo import export_hybrid
        >>> export = export_hybrid(posterior, dt=0.1, length=5.0, emergency_decel=9.0)
        >>> export.manifest.share, sorted(export.manifest.vtypes)  # 3 of 4 particles
        (0.75, ['idm_0', 'idm_1', 'idm_2'])
        >>> export.manifest.step_length, export.manifest.step_method
        (0.1, 'ballistic')
    """
    for name, value in (("dt", dt), ("length", length)):
        if not (math.isfinite(value) and value > 0):
            raise SumoError(f"{name} must be > 0, got {value}")
    if not (math.isfinite(emergency_decel) and emergency_decel > 0):
        raise SumoError(f"emergency decel must be > 0 m/s^2, got {emergency_decel}")
    total = sum(len(p) for p in posterior.hybrid.values())
    if total == 0:
        raise SumoError("the hybrid holds no particle")
    exported: dict[str, int] = {}
    skipped: dict[str, NotExported] = {}
    vtypes: dict[str, VTypeOrigin] = {}
    lines = []
    for name in posterior.models:
        particles = posterior.hybrid[name]
        if len(particles) == 0:
            continue
        mapping = MAPPINGS.get(get_model(name).name)
        if mapping is None:
            skipped[name] = NotExported(
                particles=len(particles),
                share=len(particles) / total,
                reason=NOT_IN_SUMO.get(name, "no SUMO car-following model"),
            )
            continue
        exported[name] = len(particles)
        for row in range(len(particles)):
            vtype_id = f"{name}_{row}"
            attributes = {
                "id": vtype_id,
                **mapping(
                    particles.theta[row],
                    dt=dt,
                    length=length,
                    emergency_decel=emergency_decel,
                ),
                "probability": 1.0 / total,
            }
            pair_id = int(particles.pair_ids[row])
            vtypes[vtype_id] = VTypeOrigin(model=name, row=row, pair_id=pair_id)
            body = " ".join(
                f"{k}={quoteattr(_value(v))}" for k, v in attributes.items()
            )
            lines.append(f"        <vType {body}>")
            lines.append(f'            <param key="torchcf.model" value="{name}"/>')
            lines.append(
                f'            <param key="torchcf.pair_id" value="{pair_id}"/>'
            )
            lines.append("        </vType>")
    if not exported:
        listed = ", ".join(f"{n} ({s.particles})" for n, s in skipped.items())
        raise SumoError(
            f"no particle of a model SUMO has (IDM) in the hybrid; it holds {listed}"
        )
    share = sum(exported.values()) / total
    header = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        "<!-- torchcf: the learned hybrid's particles of the models SUMO has.",
        f"     dataset {posterior.dataset}; {total} particles in the hybrid; this file "
        f"carries {sum(exported.values())} of them, a share of {share:.6f}.",
        *(
            f"     exported: {name}, {count} particles"
            for name, count in exported.items()
        ),
        *(
            f"     NOT exported: {name}, {s.particles} particles "
            f"(share {s.share:.6f}): {s.reason}"
            for name, s in skipped.items()
        ),
        "     Each vType's probability is its mass 1/P in the whole hybrid; SUMO",
        "     normalises within the distribution, so a vehicle of type "
        f"{DISTRIBUTION_ID} draws",
        "     among the exported particles only. Run SUMO with the options",
        f"     step-length {dt!r} and step-method.ballistic true (torchcf's",
        "     kinematics, SPEC section 2). -->",
        "<additional>",
        f'    <vTypeDistribution id="{DISTRIBUTION_ID}">',
    ]
    xml = "\n".join([*header, *lines, "    </vTypeDistribution>", "</additional>", ""])
    manifest = ExportManifest(
        format="torchcf.sumo.export/1",
        dataset=posterior.dataset,
        distribution=DISTRIBUTION_ID,
        file=VTYPES_FILE,
        particles=total,
        exported=exported,
        not_exported=skipped,
        share=share,
        step_length=float(dt),
        step_method="ballistic",
        length=float(length),
        emergency_decel=float(emergency_decel),
        vtypes=vtypes,
    )
    return Export(xml, manifest)


def run_constants(cfg: TrainConfig, posterior: Posterior) -> tuple[float, float]:
    """``(dt, leader_length)`` of a trained run's data [s, m]: the registry's for a
    named data set, else the config's, else the training split's own (loaded;
    the test split's are the same, and data may have none)."""
    if posterior.dataset in DATASETS:
        spec = DATASETS[posterior.dataset]
        return spec.dt, spec.leader_length
    if cfg.data.dt is not None and cfg.data.leader_length is not None:
        return cfg.data.dt, cfg.data.leader_length
    train = load_split(cfg.data, require_test=False)[0]
    return train.dt, train.leader_length


def write_export(export: Export, out_dir: str | os.PathLike[str]) -> tuple[Path, Path]:
    """Write ``hybrid.vtypes.add.xml`` and ``export.json`` into ``out_dir``
    (created; each write atomic).

    Returns:
        the two paths.

    Examples:
        >>> import tempfile
        >>> import torch
        >>> from torchcf.posterior import ModelParticles, Posterior
        >>> def particles(theta):  # one model's particles in the hybrid (SI)
        ...     n = len(theta)
        ...     return ModelParticles(
        ...         ("a", "b", "v0", "T", "s0", "delta")[: len(theta[0])],
        ...         torch.tensor(theta).double(), torch.zeros(n).double(),
        ...         torch.arange(n), torch.arange(n),
        ...     )
        >>> hybrid = {
        ...     "idm": particles([[1.5, 2.0, 33.0, 1.2, 2.0, 4.0]] * 3),
        ...     "ovm": particles([[0.8, 1.5, 30.0, 20.0]]),  # OVM's four parameters
        ... }
        >>> posterior = Posterior(
        ...     "demo", "per_pair", 1, ("idm", "ovm"), {"idm": 0.75, "ovm": 0.25},
        ...     torch.arange(4), hybrid, {"idm": {}, "ovm": {}},
        ... )
        >>> from torchcf.sumo import export_hybrid, write_export
        >>> export = export_hybrid(posterior, dt=0.1, length=5.0)
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     paths = write_export(export, folder)
        ...     print([path.name for path in paths])
        ['hybrid.vtypes.add.xml', 'export.json']
    """
    out = Path(out_dir)
    ensure_directory(out, "export directory")
    xml_path, manifest_path = out / VTYPES_FILE, out / MANIFEST_FILE
    atomic_write_text(xml_path, export.xml)
    write_json(manifest_path, export.manifest.to_json())
    return xml_path, manifest_path


__all__ = [
    "DISTRIBUTION_ID",
    "EMERGENCY_DECEL",
    "MANIFEST_FILE",
    "MAPPINGS",
    "NOT_IN_SUMO",
    "TOP_SPEED",
    "VTYPES_FILE",
    "Export",
    "ExportManifest",
    "NotExported",
    "VTypeOrigin",
    "export_hybrid",
    "idm_vtype",
    "run_constants",
    "write_export",
]
