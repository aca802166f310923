"""Model-error check: do the data fit the identified second-order model as well as noise alone allows?

The bootstrap bands and the simulated bias (`bootstrap`) are computed as if eq. 7.9 held.  A joint that is
not second order in the perturbation's band (a neighbouring joint that yields to the perturbation,
actuator dynamics between the torque sensor and the joint, a nonlinearity the linearisation misses)
leaves the estimate off by more than the bands say, and nothing in the bands shows it.  The equation
residual of eq. 9.6 does: at every instant the centred TLS fit's smallest eigenvalue (eq. 9.13) is the
residual sum of squares of the pooled equations, which the noise alone sets when the model holds.

What the noise alone gives is measured on the data's twin: the identified I(t), B(t), K(t) (smoothed over
50 ms, never across a step found, as in `simulated_bias`) driven by each cycle's measured torque
perturbation (`free_run`, from the pre-filtered initial state), with white noise at the measured levels
(second-difference estimates, `noise_std`) added to angle and torque.  The twin satisfies the model
exactly and has the data's perturbation, movement, cycles and noise; both go through the same centred
fit (the estimate's pre-filter, lags and pooling, the measured noise ratio), and

    ratio = median over the cycle of lambda_data(c) / lambda_twin(c)

is about 1 (0.85-0.99 on the elbow's and forearm's truths) when the model explains the data as the noise
does, and grows with the part of the residual the model leaves.  The median ignores the instants at steps
of K, where both fits straddle the step.  The ratio is not made for an IV estimate: the voluntary torque
that made it IV is in the data's residual and in no twin.

What it can see is bounded by the noise: a model error that a second-order model with slightly different
I, B, K absorbs in the perturbation's band (a compromise within a few per cent) leaves the residual at the
noise's level and passes.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from closedloop.impedance.data import Ensemble

RATIO_ALARM = 1.25  # data / twin equation-residual ratio above which the model is called inadequate


@dataclass
class ModelCheck:
    """Result of `model_check`: median equation-residual ratio of the data to its noise-only twin, the
    threshold and the verdict (`fires`)."""

    ratio: float
    threshold: float
    fires: bool

    def summary(self) -> dict:
        return {"residual_ratio": round(self.ratio, 4), "threshold": self.threshold, "model_error": self.fires}

    def line(self) -> str:
        return (
            f"model check: equation residual {self.ratio:.2f} times that of the model's noise-only twin "
            f"(alarm above {self.threshold:g})"
        )

    def warning(self) -> str:
        return (
            "the model does not explain the data as the noise does (equation residual "
            f"{self.ratio:.2f} times that of the identified model's noise-only twin, alarm above "
            f"{self.threshold:g}): the bands and the expected error do not cover the model error; the joint is "
            "not second order in the perturbation's band (a neighbouring joint that yields, actuator dynamics, "
            "a nonlinearity) and I, B, K may be off by several times the bands"
        )


def twin(ens: Ensemble, est, seed: int = 0, smooth_ms: float = 50.0) -> Ensemble:
    """The data's noise-only twin (module docstring): the identified model of `est` (smoothed over
    `smooth_ms`, never across a step found) driven by each cycle's measured torque perturbation from its
    pre-filtered initial state, with white noise at the measured levels added to angle and torque."""
    from closedloop.impedance.bootstrap import model_response
    from closedloop.impedance.estimate import noise_std

    dth, dtau, _ = ens.deltas()
    s_th, s_tau = noise_std(dth), noise_std(dtau)
    _, x = model_response(ens, est, smooth_ms)
    rng = np.random.default_rng(seed)
    return replace(
        ens,
        angle=ens.angle.mean(0) + x + s_th * rng.standard_normal(x.shape),
        torque=ens.torque + s_tau * rng.standard_normal(x.shape),
    )


def equation_residuals(ens: Ensemble, opt) -> np.ndarray:
    """Per instant, the centred TLS fit's residual sum of squares over the pooled equations of eq. 9.6
    (the smallest eigenvalue of eq. 9.13's moment matrix), with the pre-filter, lags, pooling and noise
    ratio of `opt`."""
    from closedloop.impedance.estimate import design, moments, pool, single_thread, tls

    half = int(round(opt.pool_ms * 1e-3 * ens.fs))
    with single_thread():
        return tls(pool(moments(design(ens, opt))[0], half), want_cond=False)[2]


def model_check(ens: Ensemble, est, seed: int = 0) -> ModelCheck | None:
    """The data's equation residual against its noise-only twin's (module docstring); the model is called
    inadequate above `RATIO_ALARM`.  None for an IV or thesis estimate (see the module docstring)."""
    from closedloop.impedance.estimate import noise_std

    if est.options.method not in ("default", "ols"):
        return None
    dth, dtau, _ = ens.deltas()
    ratio_noise = max(noise_std(dth), 1e-300) / max(noise_std(dtau), 1e-300)
    form = replace(est.options, method="default", noise_ratio=ratio_noise, edges=False, auto_iv=False)
    r_data, r_twin = equation_residuals(ens, form), equation_residuals(twin(ens, est, seed=seed), form)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = float(np.nanmedian(r_data / r_twin))
    return ModelCheck(ratio=ratio, threshold=RATIO_ALARM, fires=bool(ratio > RATIO_ALARM))
