"""Evaluation of a learned particle set on held-out pairs (SPEC section 6).

- :mod:`torchcf.evaluation.metrics`: WS, beta-WS, minimum distance, Sinkhorn and the
  average errors, from a cost matrix ``C (P, N)``;
- :mod:`torchcf.evaluation.entropic`: the Sinkhorn solver (log-domain, over-relaxed,
  several cost matrices in one batched call, bounded iterations);
- :mod:`torchcf.evaluation.report`: the paper's comparison tables (Markdown);
- :mod:`torchcf.evaluation.plots`: the figures (shares, pairwise, radar, error
  evolution, calibration curves, the loop's figures);
- :mod:`torchcf.evaluation.coverage`: predictive coverage, the fraction of
  observed spacing and speed inside the central bands of a learned set's
  simulated draws (weighted quantiles, calibration curve);
- :mod:`torchcf.evaluation.bootstrap`: bootstrap over test pairs, percentile
  intervals of the metrics recomputed on each resample, paired differences;
- :mod:`torchcf.evaluation.uncertainty`: both assembled into the keys of
  ``metrics.json``, the report and TensorBoard;
- :mod:`torchcf.evaluation.evaluate`: :func:`~torchcf.evaluation.evaluate.evaluate_run`,
  a run's test-split evaluation, its report and ``metrics.json``.

The records of ``metrics.json`` (:class:`~torchcf.runs.metrics.Evaluation` and
its parts, :class:`~torchcf.runs.metrics.SetMetrics` among them) are
:mod:`torchcf.runs.metrics`'s.
"""
