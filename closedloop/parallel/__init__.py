"""Where work runs: serially, on local processes or on a Ray cluster, with the same results.

`executor` (`run`, `imap`: jobs in order, failures isolated, resumable), `engine` (the engine protocol and
the serial engine), `engines` (local processes and Ray).
"""
