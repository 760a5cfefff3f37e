"""RunLogger writes the tags TensorBoard reads back; the figures render headless."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import (
    DEFAULT_SIZE_GUIDANCE,
    EventAccumulator,
)
from tensorboard.plugins.hparams import plugin_data_pb2

from tests.runs import run_summary
from torchcf.evaluation.plots import (
    figure_to_array,
    hybrid_images,
    pairwise_figure,
    save_figure,
    shares_figure,
)
from torchcf.runs.tensorboard import RunLogger, markdown_summary

MODELS = ("idm", "gfm")
_IDM = run_summary(MODELS).per_model["idm"]
SUMMARY = run_summary(
    MODELS,
    dataset="hdv",
    n_train=12,
    shares={"idm": 0.75, "gfm": 0.25},
    per_model={
        "idm": replace(
            _IDM,
            best_score=0.8123,
            threshold=1.5,
            invalid=400,
            particles=20_000,
            seconds=3.2,
            particles_per_s=6250.0,
        ),
        "gfm": replace(_IDM, best_score=1.1, threshold=None),
    },
    sensitivity={100: {"idm": 0.7, "gfm": 0.3}, 200: {"idm": 0.75, "gfm": 0.25}},
)


def _read(logdir: Path) -> EventAccumulator:
    events = EventAccumulator(
        str(logdir), size_guidance=dict.fromkeys(DEFAULT_SIZE_GUIDANCE, 0)
    )
    events.Reload()
    return events


def _write_run(logdir: Path) -> None:
    with RunLogger(logdir) as logger:
        for model in MODELS:
            for step, threshold in ((100, math.inf), (200, 3.0), (300, 2.0)):
                logger.progress(
                    model,
                    particles=step,
                    threshold=threshold,
                    particles_per_s=500.0,
                    invalid_rate=0.1,
                )
        theta = torch.rand(16, 2, dtype=torch.float64)
        logger.posterior("idm", ["v0", "s0"], theta)
        logger.posterior("gfm", ["v0", "tau"], theta[:0])  # empty: skipped
        images = hybrid_images(
            SUMMARY.shares, list(MODELS), torch.tensor([[1.0, 0.8], [0.2, 1.0]])
        )
        logger.hybrid(SUMMARY.shares, images, sensitivity=SUMMARY.sensitivity)
        logger.text("summary", markdown_summary(SUMMARY))
        logger.hparams(
            {
                "n_accept": 100,
                "eps": 0.5,
                "dataset": "hdv",
                "compile": False,
                "seed": None,
                "models": ["idm", "gfm"],
            },
            {"final/best_score": 0.8123},
        )


def test_run_round_trip(tmp_path: Path) -> None:
    _write_run(tmp_path)
    # One run folder: hparams must not create a timestamped sub-folder.
    assert [p for p in tmp_path.iterdir() if p.is_dir()] == []
    events = _read(tmp_path)
    tags = events.Tags()

    for tag in (
        "abc/particles/idm",
        "abc/threshold/idm",
        "abc/particles_per_s/gfm",
        "abc/invalid_rate/gfm",
        "hybrid/share/idm",
        "hybrid/share/gfm",
        "hybrid/sensitivity/N=100/idm",
        "hybrid/sensitivity/N=200/gfm",
        "final/best_score",
    ):
        assert tag in tags["scalars"], tag
    assert [e.step for e in events.Scalars("abc/particles/idm")] == [100, 200, 300]
    assert events.Scalars("hybrid/share/idm")[0].value == pytest.approx(0.75)

    assert set(tags["histograms"]) == {"posterior/idm/v0", "posterior/idm/s0"}
    assert set(tags["images"]) == {"hybrid/shares", "hybrid/pairwise"}
    image = events.Images("hybrid/pairwise")[0]
    assert image.width > 0 and image.height > 0

    # add_text("summary", ...) is a tensor event tagged "<tag>/text_summary".
    assert tags["tensors"] == ["summary/text_summary"]
    assert list(events.PluginTagToContent("text")) == ["summary/text_summary"]
    text = events.Tensors("summary/text_summary")[0].tensor_proto.string_val[0]
    assert b"| idm | 75.0 % |" in text

    hparams = events.PluginTagToContent("hparams")
    assert set(hparams) == {
        "_hparams_/experiment",
        "_hparams_/session_start_info",
        "_hparams_/session_end_info",
    }
    data = plugin_data_pb2.HParamsPluginData.FromString(
        hparams["_hparams_/session_start_info"]
    )
    values = data.session_start_info.hparams
    assert values["n_accept"].number_value == 100
    assert values["dataset"].string_value == "hdv"
    assert values["seed"].string_value == "none"
    assert values["models"].string_value == "['idm', 'gfm']"


def test_non_finite_threshold_skipped(tmp_path: Path) -> None:
    _write_run(tmp_path)
    events = _read(tmp_path)
    points = events.Scalars("abc/threshold/idm")
    assert [e.step for e in points] == [200, 300]
    assert all(math.isfinite(e.value) for e in points)


def test_disabled_writes_nothing(tmp_path: Path) -> None:
    logdir = tmp_path / "run"
    with RunLogger(logdir, enabled=False) as logger:
        assert not logger.enabled
        logger.progress(
            "idm", particles=1, threshold=1.0, particles_per_s=1.0, invalid_rate=0.0
        )
        logger.posterior("idm", ["v0"], torch.ones(3, 1))
        logger.hybrid({"idm": 1.0}, hybrid_images({"idm": 1.0}, ["idm"], [[1.0]]))
        logger.text("summary", "x")
        logger.hparams({"a": 1}, {"m": 1.0})
        logger.flush()
    assert not logdir.exists()
    assert list(tmp_path.iterdir()) == []


def test_purge_step_and_close(tmp_path: Path) -> None:
    logger = RunLogger(tmp_path, purge_step=200)
    logger.progress(
        "idm", particles=300, threshold=1.0, particles_per_s=1.0, invalid_rate=0.0
    )
    logger.close()
    logger.close()  # idempotent
    assert not logger.enabled
    assert "abc/particles/idm" in _read(tmp_path).Tags()["scalars"]


def test_posterior_shape_checked(tmp_path: Path) -> None:
    with RunLogger(tmp_path) as logger, pytest.raises(ValueError, match="theta"):
        logger.posterior("idm", ["v0", "s0"], torch.ones(4, 3))


@pytest.mark.parametrize(
    "table", [[[1.0, 0.6], [0.4, 1.0]], np.eye(2), torch.eye(2, dtype=torch.float64)]
)
def test_figures_render_rgb(table: object) -> None:
    for fig in (
        shares_figure({"idm": 0.6, "gfm": 0.4}),
        pairwise_figure(["idm", "gfm"], table),  # type: ignore[arg-type]
    ):
        image = figure_to_array(fig)
        assert image.dtype == np.uint8
        assert image.ndim == 3 and image.shape[2] == 3
        assert image.shape[0] > 50 and image.shape[1] > 50
        assert image.min() < image.max()  # something was drawn


def test_pairwise_figure_rejects_bad_shape() -> None:
    with pytest.raises(ValueError, match="shape"):
        pairwise_figure(["idm", "gfm"], np.ones((2, 3)))


def test_save_figure_png(tmp_path: Path) -> None:
    path = tmp_path / "figs" / "shares.png"
    save_figure(shares_figure({"idm": 1.0}), path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in path.parent.iterdir()] == ["shares.png"]  # no temp left


def test_markdown_summary_renders_the_runs_summary() -> None:
    text = markdown_summary(SUMMARY)
    assert "**dataset:** hdv · **training pairs:** 12" in text
    assert "| model | share |" in text
    assert "| idm | 75.0 % | 0.8123 | 1.5 | 400 | 20,000 |" in text
    assert "| gfm | 25.0 % | 1.1 | – |" in text  # no finite threshold
    assert "N=100" in text and "N=200" in text
    assert "sensitivity" not in markdown_summary(replace(SUMMARY, sensitivity={}))
