"""Solving the problem: the solver and what it needs.

`lm` (Levenberg-Marquardt on the reduced problem with its stop rules), `qr` (the reduced linear algebra),
`stages` (weighted and plain stages, starting points), `noise` (errors-in-variables weighting, thesis
eq. 4.17), `variance` (task-space noise as variance components), `robust` (robust losses and flags),
`outliers` (the screen and the robust refit), `threads` (BLAS threads).
"""
