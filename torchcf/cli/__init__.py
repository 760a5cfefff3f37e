"""The command lines: ``torchcf COMMAND [ARGS ...]``, one module per command.

    torchcf --help                        # the commands, one line each
    torchcf train configs/carII.json      # train, evaluate, the loop if configured
    torchcf train configs/carII.json --no-eval   # train only
    python -m torchcf train configs/carII.json   # the same command

- :mod:`torchcf.cli.main`: the dispatcher (the ``torchcf`` console script and
  ``python -m torchcf``, the only two entries);
- one module per command, each holding its parser and ``main(argv) -> int``:
  :mod:`~torchcf.cli.train`, :mod:`~torchcf.cli.evaluate`, :mod:`~torchcf.cli.diagnose`,
  :mod:`~torchcf.cli.crossval`, :mod:`~torchcf.cli.data`,
  :mod:`~torchcf.cli.config`, :mod:`~torchcf.cli.posterior`,
  :mod:`~torchcf.cli.sumo`, :mod:`~torchcf.cli.demo`. They parse the arguments,
  call the library (:mod:`torchcf.study.pipeline` and the stages below it) and print.

The commands sit at the top of the house: nothing in torchcf imports them, and
this package's ``__init__`` imports none of them.

Exit codes (:mod:`torchcf.system.console`): 0 done; 2 an error of the user's making or
of the machine (one line on stderr); 130 interrupted, 143 terminated.
"""
