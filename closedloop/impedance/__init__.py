"""Time-varying joint impedance identification (thesis Part II, chapters 7 and 9).

An ensemble of perturbed, repeated movements is cut into cycles and aligned, the mean removed, and at
every instant of the cycle a second-order discrete model is fitted across the ensemble and converted to
the inertia I(t), damping B(t) and stiffness K(t) of eq. 7.9.  Modules: `model` (eq. 9.20 and a numpy RK4
twin), `simulation` (the simulated experiment on either), `mujoco_sim` (the MuJoCo simulation,
finite-difference truth, a robot case), `elbow` (an independent elbow experiment for judging the
defaults), `data` (I/O, checks, segmentation, alignment), `estimate` (thesis, default, OLS, IV estimators
and the posture fit), `timing` (the cycle onsets checked against the model and re-aligned by it),
`bootstrap` (bands, free-run VAF), `nonparam` (impulse-response model check), `filters` (the
estimator's low-pass, spectrum, peak picking and smoothing in numpy), `metrics`, `results`, `plots`,
`cli`.  The package needs no scipy: its filters, spectra and peak picking are `filters`' (no
`scipy.signal`, whose import would double `identify`'s time; numbers in `filters`).
"""

_WHERE = {
    "Ensemble": "data",
    "Record": "data",
    "read_record": "data",
    "segment": "data",
    "write_record": "data",
    "EstimateOptions": "estimate",
    "ImpedanceEstimate": "estimate",
    "estimate": "estimate",
    "posture_fit": "estimate",
    "ExperimentConfig": "model",
    "ForearmParams": "model",
    "Profile": "model",
    "simulate": "simulation",
}

__all__ = list(_WHERE)


def __getattr__(name: str):
    """The public names load on first use (PEP 562): `closedloop --help` need not import scipy.signal."""
    if name in _WHERE:
        from importlib import import_module

        value = getattr(import_module(f".{_WHERE[name]}", __name__), name)
        globals()[name] = value  # `estimate` is also a submodule: the function wins, as with an eager import
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
