"""The calibrated parameters, readable: a CSV and a Markdown table per model.

A traffic engineer looks for the calibrated values first. ``posterior.pt`` holds
them as tensors; this module writes them where a spreadsheet or a report reader
finds them:

- **CSV** (:func:`parameters_csv`): one row per accepted particle of the hybrid
  (``Theta_hybrid``), columns ``model, pair_id, particle_index, score`` and then
  one column per parameter, named ``<model>.<parameter>`` (``idm.a``, ``hl.tau``:
  two models may use one name for different things), in SI units; a row leaves
  the other models' columns empty. ``pair_id`` is the training pair the particle
  was kept for (full-set column), ``particle_index`` its index in the model's
  stream (the stream regenerates it), ``score`` its weighted RMSE there.
- **Markdown** (:func:`parameters_markdown`): per model its share of the
  hybrid, its particles and pairs, and per parameter the unit, the median and
  the 5-95 % range over the model's hybrid particles (unweighted: every
  particle kept is one draw of the hybrid), the prior and the meaning.

Shapes: h particles of one model in the hybrid, K its parameters.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

import torch

from ..files import atomic_write_text
from ..models import get_model
from .learned_set import Posterior

#: Quantiles of the Markdown table's range.
RANGE = (0.05, 0.95)
#: Significant digits of values in the CSV (float64 holds 17; 10 keeps a
#: parameter's value exact to well below any physical meaning).
CSV_DIGITS = 10
#: File names in the report folder.
CSV_NAME, MARKDOWN_NAME = "parameters.csv", "parameters.md"


@dataclass(frozen=True)
class ParameterInfo:
    """What the tables say about one parameter of a model."""

    name: str
    unit: str
    lower: float | None
    upper: float | None
    meaning: str


def parameter_info(model: str, names: tuple[str, ...]) -> list[ParameterInfo]:
    """Unit, prior and meaning of each of ``model``'s parameters ``names`` (as
    the posterior lists them); a model torchcf does not know (a name from a
    newer version) keeps its names with the rest blank."""
    try:
        specs = {s.name: s for s in get_model(model).param_specs}
    except (KeyError, ValueError):
        specs = {}
    out = []
    for name in names:
        s = specs.get(name)
        if s is None:
            out.append(ParameterInfo(name, "", None, None, ""))
        else:
            out.append(ParameterInfo(name, s.unit, s.lower, s.upper, s.description))
    return out


def csv_header(posterior: Posterior) -> list[str]:
    """``model, pair_id, particle_index, score`` and ``<model>.<parameter>`` for
    every model in run order, its parameters in the model's order."""
    columns = ["model", "pair_id", "particle_index", "score"]
    for model in posterior.models:
        columns += [f"{model}.{p}" for p in posterior.hybrid[model].param_names]
    return columns


def parameters_csv(posterior: Posterior) -> str:
    """The hybrid's particles as CSV text (module docstring), models in run
    order, each model's particles by training pair, then by score."""
    header = csv_header(posterior)
    column = {name: i for i, name in enumerate(header)}
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    for model in posterior.models:
        particles = posterior.hybrid[model]
        names = [f"{model}.{p}" for p in particles.param_names]
        # (pair, score, stream index, parameters) per particle, as Python numbers
        rows = zip(
            particles.pair_ids.tolist(),
            particles.score.tolist(),
            particles.particle_index.tolist(),
            particles.theta.tolist(),
            strict=True,
        )
        for pair, score, index, theta in sorted(rows, key=lambda r: r[:3]):
            row = [""] * len(header)
            row[:4] = [model, str(pair), str(index), _number(score)]
            for name, value in zip(names, theta, strict=True):
                row[column[name]] = _number(value)
            writer.writerow(row)
    return buffer.getvalue()


def parameter_summary(posterior: Posterior, model: str) -> list[dict[str, object]]:
    """Per parameter of ``model``: its :class:`ParameterInfo` fields and the
    ``median``, ``low`` and ``high`` (:data:`RANGE` quantiles) over the model's
    hybrid particles (None without particles)."""
    particles = posterior.hybrid[model]
    theta = particles.theta.double()  # (h, K)
    out = []
    for k, info in enumerate(parameter_info(model, particles.param_names)):
        row: dict[str, object] = dict(info.__dict__)
        if len(particles):
            values = theta[:, k]
            q = torch.tensor([0.5, *RANGE], dtype=torch.float64)
            median, low, high = torch.quantile(values, q).tolist()
            row.update(median=median, low=low, high=high)
        else:
            row.update(median=None, low=None, high=None)
        out.append(row)
    return out


def parameters_markdown(posterior: Posterior, heading: str = "##") -> str:
    """A Markdown table per model (module docstring), models in run order.

    Args:
        heading: the Markdown heading of the section; each model gets one level
            more.
    """
    low, high = (f"{q:.0%}" for q in RANGE)
    lines = [
        f"{heading} Calibrated parameters",
        "",
        f"Over each model's particles in the hybrid ({posterior.dataset}, "
        f"N = {posterior.top_n} per training pair): the median and the "
        f"{low}-{high} range, SI units. One row per particle: `{CSV_NAME}`.",
        "",
    ]
    for model in posterior.models:
        particles = posterior.hybrid[model]
        share = posterior.shares.get(model, 0.0)
        pairs = len(set(particles.pair_ids.tolist()))
        lines.append(
            f"{heading}# {model.upper()}: share {share:.1%}, "
            f"{len(particles)} particles on {pairs} training pairs"
        )
        lines.append("")
        if not len(particles):
            lines += ["No particle of this model is in the hybrid.", ""]
            continue
        lines.append(
            f"| Parameter | Unit | Median | {low} | {high} | Prior | Meaning |"
        )
        lines.append("|---|---|---|---|---|---|---|")
        for row in parameter_summary(posterior, model):
            prior = (
                f"[{_short(row['lower'])}, {_short(row['upper'])}]"
                if row["lower"] is not None
                else ""
            )
            lines.append(
                f"| {row['name']} | {row['unit']} | {_short(row['median'])} | "
                f"{_short(row['low'])} | {_short(row['high'])} | {prior} | "
                f"{row['meaning']} |"
            )
        lines.append("")
    return "\n".join(lines)


def write_parameter_tables(posterior: Posterior, folder: str | Path) -> list[Path]:
    """``folder/parameters.csv`` and ``folder/parameters.md``, each written
    atomically (a reader never sees half a table).

    Raises:
        RunFileError: a file cannot be written.
    """
    folder = Path(folder)
    paths = [folder / CSV_NAME, folder / MARKDOWN_NAME]
    atomic_write_text(paths[0], parameters_csv(posterior))
    atomic_write_text(paths[1], parameters_markdown(posterior, heading="#") + "\n")
    return paths


def _number(value: float) -> str:
    return f"{value:.{CSV_DIGITS}g}"


def _short(value: object) -> str:
    """A value for the Markdown table: 4 significant digits."""
    if value is None:
        return ""
    return f"{float(value):.4g}"


__all__ = [
    "CSV_NAME",
    "MARKDOWN_NAME",
    "RANGE",
    "ParameterInfo",
    "csv_header",
    "parameter_info",
    "parameter_summary",
    "parameters_csv",
    "parameters_markdown",
    "write_parameter_tables",
]
