"""torchcf.sumo.verify: the test split replayed in SUMO, scored as torchcf scores.

Measured here (and stated in torchcf/sumo/export.py): an exported IDM vType
driving below its desired speed follows torchcf's rollout to the FCD's 9
decimals (5e-10 m); above it SUMO brakes at ``decel`` and the two part by metres.
"""

from __future__ import annotations

import json
import math

import pytest
import torch

pytest.importorskip(
    "libsumo", reason="SUMO is not installed: pip install -e '.[sumo]' (or '.[dev]')"
)

from tests.conftest import synthetic_pairs  # noqa: E402
from tests.runs import run_module  # noqa: E402
from tests.sumo.test_sumo_export import tiny_run  # noqa: E402, F401  (a fixture)
from tests.traffic.test_sampler import make_posterior  # noqa: E402
from torchcf import get_model, simulate  # noqa: E402
from torchcf.data import load_pairs  # noqa: E402
from torchcf.sumo.export import VTYPES_FILE, export_hybrid, write_export  # noqa: E402
from torchcf.sumo.verify import replay, score_cells  # noqa: E402

#: The exported vTypes' tolerance [m] below the desired speed (measured 5.0e-10 m
#: on synthetic and on the paper's car-model-2 pairs).
VTYPE_TOLERANCE = 1e-6


def _idm_posterior(v0: list[float]):
    """IDM particles with these desired speeds (the rest fixed, in the prior)."""
    posterior = make_posterior({"idm": len(v0)}, seed=1)
    theta = posterior.hybrid["idm"].theta
    theta[:, 2] = torch.tensor(v0, dtype=torch.float64)
    return posterior


def _replay_vtypes(posterior, pairs, tmp_path):
    n_particles = len(posterior.hybrid["idm"])
    write_export(
        export_hybrid(posterior, dt=pairs.dt, length=pairs.leader_length), tmp_path
    )
    cells = [(i, j) for i in range(n_particles) for j in range(pairs.n_pairs)]
    run = replay(
        pairs,
        [j for _, j in cells],
        workdir=tmp_path,
        vtypes=[f"idm_{i}" for i, _ in cells],
        additional=tmp_path / VTYPES_FILE,
    )
    ref = simulate(
        get_model("idm"), posterior.hybrid["idm"].theta, pairs, dtype=torch.float64,
        return_traj=True,
    )  # fmt: skip
    return run, ref, [j for _, j in cells]


def test_score_cells_is_spec_section_4():
    """Fed torchcf's own trajectories, the scorer gives torchcf's scores; a
    follower through its leader is invalid."""
    pairs = synthetic_pairs(n_pairs=3, n_steps=80)
    theta = make_posterior({"idm": 2}, seed=4).hybrid["idm"].theta
    ref = simulate(
        get_model("idm"), theta, pairs, dtype=torch.float64, return_traj=True
    )
    flat = [t.reshape(pairs.n_steps, -1) for t in (ref.x, ref.v, ref.a)]
    pair_index = [j for _ in range(2) for j in range(pairs.n_pairs)]
    got = score_cells(*flat, pairs, pair_index)
    for key in ("score", "e_p", "e_v", "e_a"):
        assert torch.allclose(got[key], getattr(ref, key).reshape(-1), atol=1e-12)
    crashed = flat[0].clone()
    crashed[40:, 0] = pairs.x_lead[40:, 0] + 1.0
    bad = score_cells(crashed, *flat[1:], pairs, pair_index)
    assert not bool(bad["valid"][0]) and math.isinf(float(bad["score"][0]))
    assert bool(bad["valid"][1:].all())


def test_exported_idm_below_v0_is_torchcf(tmp_path):
    pairs = synthetic_pairs(n_pairs=3, n_steps=150)
    assert float(pairs.v_follow.max()) < 30.0
    run, ref, pair_index = _replay_vtypes(_idm_posterior([32.0, 38.0]), pairs, tmp_path)
    x = ref.x.reshape(pairs.n_steps, -1)
    assert float((run.x - x).abs().max()) < VTYPE_TOLERANCE
    assert torch.allclose(run.v, ref.v.reshape(pairs.n_steps, -1), atol=1e-8, rtol=0)
    got = score_cells(run.x, run.v, run.a, pairs, pair_index)
    assert torch.allclose(got["score"], ref.score.reshape(-1), atol=1e-6)


def test_exported_idm_above_v0_parts_from_spec(tmp_path):
    """SUMO brakes at decel towards v0 where SPEC's IDM brakes by its own law:
    the documented difference, measured."""
    pairs = synthetic_pairs(n_pairs=2, n_steps=150)
    slow = float(pairs.v_follow[0].min()) - 3.0
    run, ref, _ = _replay_vtypes(_idm_posterior([slow]), pairs, tmp_path)
    assert float((run.x - ref.x.reshape(pairs.n_steps, -1)).abs().max()) > 1e-3


def test_exported_idm_on_the_papers_data(tmp_path, data_root):
    pairs = load_pairs("car-model-2", "test", data_root=data_root)
    pairs = pairs.subset([0, 1, 2])
    run, ref, _ = _replay_vtypes(_idm_posterior([40.0, 40.0]), pairs, tmp_path)
    assert float(pairs.v_follow[pairs.mask].max()) < 40.0
    x = ref.x.reshape(pairs.n_steps, -1)
    mask = pairs.mask[:, [j for _ in range(2) for j in range(3)]]
    assert float((run.x - x).abs()[mask].max()) < VTYPE_TOLERANCE


@pytest.mark.slow  # a training and a SUMO verification
def test_verify_command(tiny_run, tmp_path):  # noqa: F811
    done = run_module(
        "torchcf", "sumo", "verify", str(tiny_run), "--out", str(tmp_path)
    )
    assert done.returncode == 0, done.stderr
    report = json.loads((tmp_path / "verify.json").read_text())
    cosim, vtypes = report["cosim"], report["vtypes"]
    assert cosim["models"] == ["idm", "hl"]
    assert cosim["max_position_difference_m"] < 1e-6
    # Positions equal, so the position error is torchcf's; SUMO's acceleration
    # is the step's mean (HL: not the lag's state), so e_a differs slightly.
    assert cosim["sumo"]["e_p"] == pytest.approx(cosim["torchcf"]["e_p"], abs=1e-8)
    assert cosim["sumo"]["ws"] == pytest.approx(cosim["torchcf"]["ws"], rel=0.05)
    assert vtypes["models"] == ["idm"]
    assert vtypes["max_position_difference_at_or_below_v0_m"] < 1e-6
    table = (tmp_path / "verify.md").read_text()
    assert "SUMO co-simulation" in table and "SUMO exported vTypes" in table
    # never silent: each stage said, a bar over SUMO's steps for each replay
    for stage in ("loading the run", "torchcf's rollout", "exported vTypes",
                  "co-simulation", "co-simulation: reading SUMO's FCD"):  # fmt: skip
        assert f"sumo verify: {stage}" in done.stderr, done.stderr
