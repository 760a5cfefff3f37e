"""Shape letters: the one table that every docstring and comment of torchcf follows.

A shape is a tuple, first dimension first: ``(T, P, N)``. Its entries are

- a capital letter of the table below, which has one meaning in the whole package;
- that letter with a subscript or a prime: another size along the same dimension
  (``T_pad``, ``T'``, ``N'``, ``N_test``, ``K_drawn``, ``K_E``, ``V_g``, ``Q'``);
- a lowercase name: a size that is a value of the code at hand, an argument,
  attribute or constant of that name (``n`` of ``TopN.first(n)``, ``capacity``,
  ``copies``, ``BLOCK_STEPS``, ``stop - start``). A dimension of the table is
  written with its letter, never by a variable's name: ``(N, K)``, not
  ``(n_pairs, n_params)``;
- a number: a fixed axis, named where it appears (``2``: a box's lower and upper
  bound; ``3``: x, v, a; ``6``: the columns of the rollout's observation table);
- ``*state``: the dimensions of a rollout's state, ``(P,)`` or ``(P, N)``.

========  ====================================================  ====================
letter    dimension                                             where
========  ====================================================  ====================
``P``     particles: the rows of a parameter matrix ``theta``   sim, models, abc,
          ``(P, K)`` (inside the rollout, a chunk of them)      evaluation, tblog
``Q``     a particle set outside a buffer, one pair per entry:  abc.particles,
          candidates offered to a buffer or pooled from         abc.hybrid,
          several, the hybrid's members, a diagnosis            abc.topn, diagnose,
          population                                            posterior
``N``     leader-follower pairs                                 data, sim, abc,
                                                                evaluation, traffic
``T``     time steps of a pair set (``T_pad``: padded to whole  data, sim, synthetic,
          blocks; ``T'``: the records of a traffic run)         traffic, evaluation
``K``     parameters of one model, the columns of ``theta``     models, sim, abc,
          (``K_drawn``: those a prior stream draws; ``K_E``:    diagnose, tblog
          an effect's own)
``M``     models of a run (the hybrid's candidate models)       abc.hybrid, tblog,
                                                                evaluation.plots
``R``     replicas of a buffer, one per ``torchrun`` rank       abc.topn,
                                                                abc.distributed
``B``     QP instances (``b``: those solved in one call,        qp, models.mpc
          ``r``: those left to a later stage); the MPC solves
          one per simulated cell
``S``     scenarios of a traffic simulation                     traffic
``V``     vehicles of a traffic simulation, flattened           traffic.sampler
          (``vehicle_shape``, e.g. ``(S, n)``); ``V_g``: those
          of one model's group
``C``     channels of the amortised encoder's input             amortised
``E``     width of the amortised encoder's embedding            amortised
``J``     series the amortised networks read in one call:       amortised
          simulated examples or observed pairs
``D``     depth of a perception delay's history [steps]         models.effects
``L``     lags of a residual cross-correlation                  diagnose.residuals
``H, W``  height and width of an image                          evaluation.plots,
                                                                tblog
========  ====================================================  ====================

Lowercase sizes in common use (each the value of that name where it appears):
``n``, ``m`` in :mod:`torchcf.qp` are the variables and constraint rows of one QP
(the MPC's ``n`` is its horizon ``K``); ``n`` in :mod:`torchcf.abc` is the top-N
size, the entries kept per pair (config ``abc.top_n``); ``n`` in
:mod:`torchcf.traffic` is the vehicles per scenario (``sampler.sample((S, n))``).

Conventions:

- **Time-major.** Series and trajectories put time first: a pair set's series are
  ``(T, N)``, a rollout's trajectory ``(T, P, N)`` or ``(T, P)``, a traffic run's
  records ``(T', S, n)``.
- **Full and paired layouts.** A rollout's state, scores and errors are ``(P, N)``
  in the *full* layout (every particle on every pair) and ``(P,)`` in the *paired*
  layout (particle ``j`` on pair ``pair_index[j]``); parameters broadcast as
  ``(P, 1)`` or ``(P,)``.
- **Batch-first QPs.** The public QP types are ``(B, n)``; the kernels hold the same
  problems batch-last, ``(n, B)`` (:mod:`torchcf.qp.problem`).
- **Letters in formulas are symbols, not dimensions.** Inside an equation, or as a
  parameter's name, a letter is the paper's or the SPEC's symbol: the MPC's horizon
  ``K`` and matrices ``A, B, Q, R, H, G``, a QP's ``P`` and ``A``, the leader
  length or ring length ``L``, IDM's time gap ``T``, GFM's ``K``, a cost matrix
  ``C``, the big-M cost ``M``. The table's letters hold inside shape tuples and in
  counts such as "N pairs".
- **top-N** is the name of the SPEC's per-pair buffer; its size is ``n``, never
  ``N``. Output text keeps its form (the TensorBoard tag ``hybrid/sensitivity/N=<n>``).

Nothing to import: the module holds this table only.
"""
