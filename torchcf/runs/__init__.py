"""A run on disk: its directory, the records of its files and its TensorBoard log.

- :mod:`.directory`: :class:`~torchcf.runs.directory.RunDir`, the layout of a
  run directory (config, checkpoint, posterior, summary, report), its lock and
  the checks on resume; it writes and reads the records below;
- :mod:`.summary`: what ``summary.json`` holds,
  :class:`~torchcf.runs.summary.RunSummary` (a training's) and
  :class:`~torchcf.runs.summary.RecalibrationSummary` (a re-calibration's);
- :mod:`.metrics`: what ``metrics.json`` holds,
  :class:`~torchcf.runs.metrics.Evaluation` (a run's test-split evaluation) and
  :class:`~torchcf.runs.metrics.CrossvalResult` (a cross-validation's);
- :mod:`.tensorboard`: :class:`~torchcf.runs.tensorboard.RunLogger`, the
  run's TensorBoard events.
"""
