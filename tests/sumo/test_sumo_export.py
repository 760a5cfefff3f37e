"""torchcf.sumo.export: the hybrid's IDM particles as SUMO vTypes, the mapping
checked by hand and against SUMO's own IDM step."""

from __future__ import annotations

import json
import math
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import torch

from tests.runs import run_module, write_config, write_data
from tests.traffic.test_sampler import make_posterior
from torchcf.sumo import backend
from torchcf.sumo.backend import SumoError, SumoMissingError
from torchcf.sumo.export import (
    DISTRIBUTION_ID,
    MANIFEST_FILE,
    NOT_IN_SUMO,
    VTYPES_FILE,
    ExportManifest,
    export_hybrid,
    idm_vtype,
    write_export,
)

#: a, b, v0, T, s0, delta
THETA = torch.tensor([1.2, 2.0, 30.0, 1.5, 2.0, 4.0], dtype=torch.float64)


def test_idm_mapping_by_hand():
    attributes = idm_vtype(THETA, dt=0.1, length=5.0, emergency_decel=9.0)
    assert attributes == {
        "carFollowModel": "IDM",
        "accel": 1.2,
        "decel": 2.0,
        "desiredMaxSpeed": 30.0,  # the IDM's v0
        "maxSpeed": 55.56,  # the car's top speed
        "speedFactor": 1.0,
        "speedDev": 0.0,
        "tau": 1.5,
        "minGap": 2.0,
        "delta": 4.0,
        "stepping": 0.1,  # one internal IDM step per SUMO step
        "emergencyDecel": 9.0,
        "length": 5.0,
    }
    # SUMO needs emergencyDecel >= decel: a particle braking harder keeps its b.
    hard = THETA.clone()
    hard[1] = 12.0
    assert idm_vtype(hard, dt=0.1, length=5.0, emergency_decel=9.0)[
        "emergencyDecel"
    ] == pytest.approx(12.0)


def test_export_lists_what_it_leaves_out(tmp_path):
    posterior = make_posterior({"idm": 3, "hl": 2, "ovm": 1, "mpc": 0})
    export = export_hybrid(posterior, dt=0.1, length=5.0)
    manifest = export.manifest
    assert manifest.exported == {"idm": 3}
    assert manifest.share == pytest.approx(0.5)
    assert set(manifest.not_exported) == {"hl", "ovm"}  # mpc holds no particle
    assert manifest.not_exported["hl"].particles == 2
    assert manifest.not_exported["hl"].reason == NOT_IN_SUMO["hl"]
    assert manifest.not_exported["ovm"].share == pytest.approx(1 / 6)

    xml_path, manifest_path = write_export(export, tmp_path)
    assert (xml_path.name, manifest_path.name) == (VTYPES_FILE, MANIFEST_FILE)
    on_disk = json.loads(manifest_path.read_text())
    assert on_disk == manifest.to_json() and list(on_disk) == list(manifest.to_json())
    assert ExportManifest.from_json(on_disk) == manifest
    text = xml_path.read_text()
    assert "NOT exported: hl, 2 particles" in text and "share of 0.500000" in text
    root = ET.parse(xml_path).getroot()
    (distribution,) = root.findall("vTypeDistribution")
    assert distribution.get("id") == DISTRIBUTION_ID
    vtypes = distribution.findall("vType")
    assert [v.get("id") for v in vtypes] == ["idm_0", "idm_1", "idm_2"]
    theta = posterior.hybrid["idm"].theta
    for row, vtype in enumerate(vtypes):
        # Full precision: the float read back is the particle's own.
        assert float(vtype.get("accel")) == float(theta[row, 0])
        assert float(vtype.get("minGap")) == float(theta[row, 4])
        assert float(vtype.get("probability")) == pytest.approx(1 / 6)


def test_export_without_an_idm_particle_says_so():
    with pytest.raises(SumoError, match=r"no particle of a model SUMO has.*hl \(2\)"):
        export_hybrid(make_posterior({"hl": 2}), dt=0.1, length=5.0)
    with pytest.raises(SumoError, match="dt must be > 0"):
        export_hybrid(make_posterior({"idm": 1}), dt=0.0, length=5.0)


def test_missing_sumo_names_the_extra(monkeypatch):
    # None in sys.modules: the import raises ImportError, as when not installed.
    monkeypatch.setitem(sys.modules, "libsumo", None)
    monkeypatch.setitem(sys.modules, "sumo", None)
    with pytest.raises(SumoMissingError, match=r"pip install 'torchcf\[sumo\]'"):
        backend.require_libsumo()
    with pytest.raises(SumoMissingError, match=r"torchcf\[sumo\]"):
        backend.binary("netconvert")


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    """A trained run (IDM and HL) on synthetic data, without evaluation."""
    folder = tmp_path_factory.mktemp("run")
    data = write_data(folder / "data", n_pairs=6, n_steps=100)
    config = write_config(
        folder / "config.json",
        data,
        abc={"n_particles": 2000, "chunk_size": 500},
        models=["idm", "hl"],
    )
    done = run_module(
        "torchcf", "train", str(config), "--out", str(folder / "run"), "--no-eval"
    )
    assert done.returncode == 0, done.stderr
    return folder / "run"


@pytest.mark.slow  # a training and a SUMO export
def test_export_command(tiny_run, tmp_path):
    done = run_module(
        "torchcf", "sumo", "export", str(tiny_run), "--out", str(tmp_path)
    )
    assert done.returncode == 0, done.stderr
    assert "not exported: hl" in done.stdout
    root = ET.parse(tmp_path / VTYPES_FILE).getroot()
    assert root.find("vTypeDistribution").findall("vType")


@pytest.mark.parametrize(
    "args, message",
    [
        (
            ["export", "{run}", "--out", "{tmp}", "--length", "-1"],
            "--length: expected a number > 0",
        ),
        (["export", "{tmp}/nothing", "--out", "{tmp}"], "holds no finished run"),
        (
            ["verify", "{run}", "--max-particles", "0"],
            "--max-particles: expected a whole",
        ),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tiny_run, tmp_path, args, message):
    argv = [a.format(run=tiny_run, tmp=tmp_path) for a in args]
    done = run_module("torchcf", "sumo", *argv)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0]


def test_sumo_takes_one_idm_step_as_spec(tmp_path):
    """SUMO's IDM with the exported vType, one step from a hand-set state,
    against SPEC's IDM worked out by hand (ballistic update, stepping = dt)."""
    pytest.importorskip(
        "libsumo", reason="SUMO is not installed: pip install -e '.[sumo]'"
    )
    from torchcf.sumo.network import straight_edges

    dt, length = 0.1, 5.0
    a, b, v0, T, s0, delta = THETA.tolist()
    posterior = make_posterior({"idm": 1})
    posterior.hybrid["idm"].theta[0] = THETA
    write_export(export_hybrid(posterior, dt=dt, length=length), tmp_path)
    net = straight_edges(1, 1000.0, tmp_path)
    # Follower at 10 m, 20 m/s; the leader's back 30 m ahead at 15 m/s (its
    # front 35 m ahead): SUMO's bumper gap g = 30 m plays SPEC's s.
    (tmp_path / "r.rou.xml").write_text(
        '<routes><vType id="lead" length="5" minGap="0" maxSpeed="50"/>'
        '<route id="r" edges="e0"/>'
        '<vehicle id="L" type="lead" route="r" depart="0" departPos="45" '
        'departSpeed="15" insertionChecks="none"/>'
        '<vehicle id="F" type="idm_0" route="r" depart="0" departPos="10" '
        'departSpeed="20" insertionChecks="none"/></routes>'
    )
    s, v, v_lead = 30.0, 20.0, 15.0
    s_star = s0 + max(0.0, v * T - v * (v_lead - v) / (2 * math.sqrt(a * b)))
    u = a * (1 - (v / v0) ** delta - (s_star / s) ** 2)  # = -0.7941... m/s^2
    arguments = [
        "--net-file", str(net), "--route-files", str(tmp_path / "r.rou.xml"),
        "--additional-files", str(tmp_path / VTYPES_FILE),
        "--step-length", "0.1", "--step-method.ballistic", "true",
        "--no-step-log", "true",
    ]  # fmt: skip
    with backend.running(arguments) as sumo:
        sumo.simulationStep()
        sumo.vehicle.setSpeedMode("L", 0)
        sumo.vehicle.setSpeed("L", v_lead)
        sumo.simulationStep()
        v_next = sumo.vehicle.getSpeed("F")
        x_next = sumo.vehicle.getLanePosition("F")
    assert v_next == pytest.approx(v + u * dt, abs=1e-12)
    assert x_next == pytest.approx(10.0 + v * dt + u * dt**2 / 2, abs=1e-12)
