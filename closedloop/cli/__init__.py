"""The command line: `closedloop <command>` (`main`), one module per command family.

`main` builds the parser and runs a command with its exit code; `calibrate`, `evaluate` (rigs),
`simulate`, `sweep` (many datasets), `impedance` (Part II) and `tools` (inspect, loops, extract, check,
report) hold the commands; `parse` the option types.
"""
