"""The study of a config and its variants, the top of the library.

- :mod:`.pipeline`: :func:`~torchcf.study.pipeline.run_study` (train, evaluate
  on the test split, the loop where configured) and its stages;
- :mod:`.crossval`: k-fold cross-validation, one study per fold;
- :mod:`.demo`: each model's prior particles rolled out (``torchcf demo``).
"""
