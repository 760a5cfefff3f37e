"""Evaluation of a learned particle set on held-out pairs (SPEC section 6).

- :mod:`torchcf.evaluation.metrics`: WS, beta-WS, minimum distance, Sinkhorn and the
  average errors, from a cost matrix ``C (P, N)``;
- :mod:`torchcf.evaluation.entropic`: the Sinkhorn solver (log-domain, over-relaxed,
  several cost matrices in one batched call, bounded iterations);
- :mod:`torchcf.evaluation.report`: the paper's comparison tables (Markdown);
- :mod:`torchcf.evaluation.plots`: the figures (shares, pairwise, radar, error
  evolution, the loop's figures).
"""
