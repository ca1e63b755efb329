"""The model-based inverse: the leg as the cascade sees it, fitted to a few step responses.

:func:`fit_leg_plant` fits an inertia scale, a payload on the foot, viscous and Coulomb
friction on the nominal five-bar to a handful of measured steps (:func:`fitting_gains`
chooses them), so a changed leg (a payload) needs a few experiments, not a new sweep;
:class:`LegPlantModel` then answers ``gains_for(zeta, fn)`` on that model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from ..errors import IdentificationError
from ..experiments.step import StepResponse
from ..identify.step import second_order
from ..model.cascade import motor_side_inertia
from ..model.drive import AxisMap
from ..model.dynamics import mass_matrix
from ..model.kinematics import foot_position
from ..params import load_plant
from ..twin.host import Twin


def twin_step_responses(twin, gains, step=0.4, duration=1.5, sample_period=0.002):
    """Listing 7.4's steps on a :class:`leglib.twin.host.Twin` for each gain triple (one batch),
    as :class:`leglib.experiments.step.StepResponse` with the foot height of the twin's nominal
    leg; the configuration's step velocity limit, an abort at twice the step."""
    g = np.atleast_2d(np.asarray(gains, float))
    out = twin.step_batch(g, step_turns=step, duration=duration, sample_period=sample_period,
                          vel_limit=twin.config.step_vel_limit, abort_error_turns=2 * abs(step))
    ax = twin.axes
    res = []
    for i in range(len(g)):
        q1 = ax.counts_to_joint(out["counts"][i, :, ax.axis_of_joint[0]], 0)
        q2 = ax.counts_to_joint(out["counts"][i, :, ax.axis_of_joint[1]], 1)
        _, y = foot_position(twin.nominal_leg, q1, q2)
        res.append(StepResponse(t=out["t"], q1=q1, q2=q2, y=y, gains=tuple(g[i]), step=step,
                                completed=bool(out["abort_tick"][i] < 0)))
    return res


@dataclass
class LegPlantModel:
    """The leg as the cascade sees it, from a handful of step responses: the nominal
    five-bar's geometry with a fitted inertia scale, a payload on the foot [kg] and joint
    friction (viscous, Coulomb; the same on both joints), simulated through the same
    compiled cascade as the twin, without noise or quantization. ``params`` holds the fitted values, ``experiments`` how many step
    responses it took, ``rms_turns`` the fit's motor-position residual."""

    params: dict
    template: object
    config: object
    step: float
    duration: float
    sample_period: float
    rms_turns: float
    experiments: int

    def twin(self):
        p = self.params
        plant = self.template.replace(inertia_scale=p["inertia_scale"], mass_scale=1.0,
                                      viscous1=p["viscous"], viscous2=p["viscous"], coulomb1=p["coulomb"],
                                      coulomb2=p["coulomb"], stribeck1=0.0, stribeck2=0.0,
                                      payload_mass=p["payload_mass"])
        # exact positions: finite differences of the fit must see small parameter changes
        return Twin(plant, self.config, noise=False, quantize=False)

    def responses(self, gains):
        """Simulated :class:`leglib.experiments.step.StepResponse` for each gain triple (batch)."""
        return twin_step_responses(self.twin(), gains, self.step, self.duration, self.sample_period)

    def predict(self, gains) -> tuple[float, float]:
        """(zeta, fn [Hz]) the model predicts for one gain triple (NaN if unstable or not a
        second-order step)."""
        r = self.responses([gains])[0]
        if not r.completed:
            return math.nan, math.nan
        try:
            f = second_order(r.t, r.y)
        except IdentificationError:
            return math.nan, math.nan
        return f.zeta, f.fn

    def gains_for(self, zeta: float, fn: float, vel_integrator_gain: float = 0.01, start=None):
        """Gains giving (zeta, fn [Hz]) on the model: Kp, Kv solved (log space, bounded by
        the configuration) from the analytic PD start; returns (gains, predicted (zeta, fn))."""
        cfg = self.config
        lo = np.log([1.0, 1e-3])
        hi = np.log([cfg.max_pos_gain, cfg.max_vel_gain])
        if start is None:
            # PD on the model leg's opening-mode inertia at rest, seen at the motor:
            # wn^2 = Kv Kp / J, 2 zeta wn J = Kv
            tw = self.twin()
            D = mass_matrix(tw.leg, *tw.leg.q0)
            J = motor_side_inertia(D[0, 0] - D[0, 1], tw.axes.gear_ratio)
            wn = 2 * math.pi * fn
            kv = 2 * zeta * wn * J
            start = (wn ** 2 * J / kv, kv)
        starts = [np.log(start)] + [np.log(start) + d for d in ([0.0, -0.4], [0.0, 0.4])]

        def resid(x):
            z, f = self.predict((math.exp(x[0]), math.exp(x[1]), vel_integrator_gain))
            if not np.isfinite(z):
                return np.array([2.0, 2.0])
            return np.array([z / zeta - 1, f / fn - 1])

        best = None
        for x0 in starts:  # a second start only when the first does not reach the target
            res = least_squares(resid, np.clip(x0, lo + 1e-6, hi - 1e-6), bounds=(lo, hi), diff_step=1e-3,
                                max_nfev=60)
            if best is None or res.cost < best.cost:
                best = res
            if np.max(np.abs(best.fun)) < 0.005:
                break
        gains = (math.exp(best.x[0]), math.exp(best.x[1]), vel_integrator_gain)
        return gains, self.predict(gains)


def fit_leg_plant(responses, config, template="default") -> LegPlantModel:
    """Fit :class:`LegPlantModel` to measured step responses (least squares on both axes'
    motor positions). ``template`` supplies the structure (base leg, stops); its friction,
    inertia and mass values are not used. Unstable responses are skipped."""

    template = load_plant(template) if isinstance(template, str) else template
    done = [r for r in responses if r.completed]
    if len(done) < 2:
        raise ValueError(f"need at least two completed step responses, got {len(done)}")
    r0 = done[0]
    dt = float(r0.t[1] - r0.t[0])
    model = LegPlantModel(params={}, template=template, config=config, step=float(r0.step),
                          duration=float(len(r0.t) * dt), sample_period=dt, rms_turns=math.nan,
                          experiments=len(responses))
    ax = AxisMap.from_leg(template.base_leg())
    meas = np.concatenate([np.concatenate([ax.motor_turns(r.q1, 0), ax.motor_turns(r.q2, 1)]) for r in done])
    gains = np.array([r.gains for r in done])
    names = ("inertia_scale", "payload_mass", "viscous", "coulomb")

    def resid(x):
        model.params = dict(zip(names, np.exp(x)))
        sims = model.responses(gains)
        n = min(len(s.t) for s in sims)
        sim = np.concatenate([np.concatenate([ax.motor_turns(s.q1, 0), ax.motor_turns(s.q2, 1)]) for s in sims])
        return sim - meas if sim.size == meas.size and n == len(r0.t) else np.full(meas.size, 1.0)

    x0 = np.log([1.0, 0.05, 0.003, 0.01])
    res = least_squares(resid, x0, bounds=(np.log([0.2, 1e-4, 1e-5, 1e-5]), np.log([5.0, 5.0, 0.2, 0.3])),
                        diff_step=1e-3)
    model.params = dict(zip(names, map(float, np.exp(res.x))))
    model.rms_turns = float(np.sqrt(np.mean(res.fun ** 2)))
    return model


def fitting_gains(count: int = 5, pos_range=(25.0, 50.0), vel_range=(0.03, 0.15),
                  vel_integrator_gain: float = 0.01) -> np.ndarray:
    """``count`` gain triples for fitting :class:`LegPlantModel`: pos_gain and vel_gain
    spread over moderate, stable ranges in different orders (so damping and stiffness vary
    independently across the experiments), a small fixed integrator gain."""
    pos = np.linspace(*pos_range, count)
    vel = np.roll(np.linspace(*vel_range, count)[::-1], 1)
    return np.column_stack([pos, vel, np.full(count, vel_integrator_gain)])
