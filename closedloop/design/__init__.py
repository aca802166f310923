"""Choosing the configurations to record: the most informative poses (D- and A-optimal designs).

`poses` (`select_poses` and the pool), `optimal` (greedy and DETMAX designs), `exchange` (exchange
algorithms).
"""
