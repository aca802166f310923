"""The command line: `closedloop <command>` (`main`), one module per command family.

`main` builds the parser and runs a command with its exit code (inspect and check in it); `calibrate`
(its arguments derived from `closedloop.run.options`, the run is `closedloop.run`), `evaluate`,
`simulate` (with `--robot`), `sweep` (many datasets), `extract`, `loops` and `impedance` (Part II)
hold the commands; `config` applies ``--config`` files, `parse` the option types.
"""
