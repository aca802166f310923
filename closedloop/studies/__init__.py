"""Studies of the estimator: Monte Carlo against the Cramer-Rao bound, the thesis's hand, truths.

`montecarlo`, `hand` (the Utah/MIT finger of thesis ch. 4), `truth` (drawing a true robot and exact
datasets for a loop), `synthetic` (self-motion of a closed chain).
"""
