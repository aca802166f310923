"""Is the calibration right? Held-out data, other fixtures, other logs, a known truth.

`kfold` (k-fold validation of a calibration), `fixtures` (leave one fixture out), `evaluate` (a model on
data it was not fitted to), `check` (a calibration against a simulation's ground truth).
"""
