"""Time-varying joint impedance identification (thesis Part II, chapters 7 and 9).

An ensemble of perturbed, repeated movements is cut into cycles and aligned, the mean removed, and at
every instant of the cycle a second-order discrete model is fitted across the ensemble and converted to
the inertia I(t), damping B(t) and stiffness K(t) of eq. 7.9.  Modules: `model` (eq. 9.20 and a numpy RK4
twin), `mujoco_sim` (the MuJoCo simulation, finite-difference truth, a robot case), `data` (I/O,
segmentation, alignment), `estimate` (thesis, default, OLS, IV estimators and the posture fit),
`bootstrap` (bands, free-run VAF), `nonparam` (impulse-response model check), `metrics`, `results`,
`plots`, `cli`.  The estimator needs only numpy and scipy.
"""

from .data import Ensemble, Record, read_record, segment, write_record
from .estimate import EstimateOptions, ImpedanceEstimate, estimate, posture_fit
from .model import ExperimentConfig, ForearmParams, Profile, simulate

__all__ = ["Ensemble", "Record", "read_record", "segment", "write_record", "EstimateOptions",
           "ImpedanceEstimate", "estimate", "posture_fit", "ExperimentConfig", "ForearmParams", "Profile",
           "simulate"]
