"""The robot model: kinematics and the parameters a calibration can change.

`robot` (`RobotModel`: URDF, MJCF or D-H on Pinocchio, frames, joints), `dh` (D-H tables), `parameters`
(the per-joint placement, offset, scale and compliance parameters and their priors), `se3` (SE(3) and so(3)
helpers: exp6, log6, adjoints, rotation vectors).
"""
