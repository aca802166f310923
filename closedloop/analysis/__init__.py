"""What the data can and cannot tell, at the start and at the solution.

`identifiability` (structural reduction: dropped and unidentifiable parameters, thesis ch. 3-4),
`selection` (which parameters to identify), `gauge` (what the data cannot see: base, size), `scale`
(what sets the robot's size and how well), `observability` (indices of an experiment), `linearity`
(do the error bars hold along the cost's profile).
"""
