"""The process's plumbing, below every stage: errors and exit codes, files
written safely, signals, the process's memory settings and the console.

- :mod:`.errors`: :class:`~torchcf.system.errors.TorchcfError`, the error a
  user can mend (one line, exit code 2), and ``did_you_mean``;
- :mod:`.files`: atomic writes, run-directory locks, folders made and removed;
- :mod:`.signals`: SIGTERM/SIGINT turned into a clean stop;
- :mod:`.process`: glibc's allocator thresholds for batched CPU work;
- :mod:`.console`: the command lines' shared plumbing (exit codes, checked
  argument types, progress-bar pacing, one-line errors);
- :mod:`.version`: the package's version (``torchcf.__version__``).

Imports nothing of torchcf but itself.
"""
