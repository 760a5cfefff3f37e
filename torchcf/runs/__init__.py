"""A run on disk: its directory and its TensorBoard log.

- :mod:`.directory`: :class:`~torchcf.runs.directory.RunDir`, the layout of a
  run directory (config, checkpoint, posterior, summary, report), its lock and
  the checks on resume;
- :mod:`.tensorboard`: :class:`~torchcf.runs.tensorboard.RunLogger`, the
  run's TensorBoard events.
"""
