"""Studies of the estimator: Monte Carlo against the Cramer-Rao bound, the thesis's hand, truths.

`montecarlo`, `hand` (the Utah/MIT finger of thesis ch. 4), `truth` (drawing a true robot and exact
datasets for a loop), `synthetic` (self-motion of a closed chain), `identifiable` (the parameters a
calibration can tell apart, read off the nominal robot's structure: no fit; the simulator's truth and
`truth` draw in it).
"""
