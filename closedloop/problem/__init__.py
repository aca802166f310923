"""The stacked calibration problem: every loop's closure at every configuration, as one residual.

`problem` (`CalibrationProblem`: parameters, blocks, the residual and its Jacobian, thesis eq. 3.8 and
4.17), `blocks` (evaluation in chunks), `shared` (loop parameters shared by name across loops), `rig`
(``--distance``, ``--block``, ``--length`` read into records), `lengths` and `distances` (known lengths
between robot frames and distances between loop points, as extra loops),
`unwrap` (rotation vectors compared across fits).
"""
