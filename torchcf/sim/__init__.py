"""The rollout: the models' one-step updates over the observed leaders.

- :mod:`.step`: one step of every model, batched over particles and pairs;
- :mod:`.compiled`: blocks of steps compiled with ``torch.compile``;
- :mod:`.rollout`: :func:`~torchcf.sim.rollout.simulate`, a whole rollout of
  particles over pairs (SPEC sections 1-2);
- :mod:`.synthetic`: pairs made by rolling models out behind made-up leaders
  (the tests' and the regression cases' data).
"""
