"""GTSAM graph assembly from a :class:`Problem`: the factors of one step, or of a whole recording."""

from __future__ import annotations

import gtsam
import numpy as np

from flexforce.errors import ConfigError
from flexforce.factors import gtsam_factors as gf


class GraphBuilder:
    """Builds the gtsam factors of each step of a Problem (noise models made once)."""

    def __init__(self, prob):
        if prob.effects:
            raise ConfigError("the gtsam graph (fixed-lag smoother) does not take effects yet; use the batch "
                              "smoother for models with effects")
        self.prob = prob
        s = prob.sigmas
        self.noise_imu = gtsam.noiseModel.Diagonal.Sigmas(s.imu)
        self.noise_ne = gtsam.noiseModel.Gaussian.Covariance(s.newton_euler_cov)
        if s.robust_k is not None:
            self.noise_ne = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(s.robust_k),
                                                           self.noise_ne)
        self.noise_contact = gtsam.noiseModel.Gaussian.Covariance(s.contact_cov)
        self.noise_ft = gtsam.noiseModel.Diagonal.Sigmas(s.ft)
        self.noise_int = gtsam.noiseModel.Gaussian.Covariance(s.integration_cov)

    def contacts(self, k: int) -> list[int]:
        return [int(i) for i in np.flatnonzero(self.prob.active[k])]

    def step_factors(self, k: int, link: bool = True) -> list:
        """Newton-Euler, contact law per active contact, IMU, F/T (if used), integration from k-1,
        and the prior at step 0."""
        p = self.prob
        contacts = self.contacts(k)
        out = [
            gf.newton_euler_factor(self.noise_ne, k, contacts, float(p.rec.mass), p.com[k], p.com_vel[k],
                                   p.com_acc[k], p.inertia[k], p.inertia_dot[k], p.sigma_l[k], p.sigma_dot[k], p.g),
            gf.imu_factor(self.noise_imu, k, p.y_imu[k], p.imu_R[k], p.imu_p[k], p.imu_v[k], p.imu_a[k],
                          p.imu_w[k], p.g),
        ]
        for i in contacts:
            out.append(gf.contact_factor(self.noise_contact, k, i, p.contact_p[k, i], p.contact_R[k, i],
                                         p.model.contact_params[i], p.rest_p[k, i], p.rest_R[k, i]))
            if p.use_ft:
                out.append(gf.ft_factor(self.noise_ft, k, i, p.contact_p[k, i], p.contact_R[k, i], p.y_ft[k, i]))
        if k > 0 and link:
            out.append(gf.integration_factor(self.noise_int, k - 1, p.dt))
        else:
            R0, q0 = p.prior_mean
            out.extend(gf.state_prior_factors(0, R0, q0, p.sigmas.prior))
        return out

    def graph(self, k0: int = 0, k1: int | None = None) -> gtsam.NonlinearFactorGraph:
        """All factors of steps ``k0 .. k1-1`` (integration factors inside the range only)."""
        k1 = self.prob.n if k1 is None else k1
        graph = gtsam.NonlinearFactorGraph()
        for k in range(k0, k1):
            for f in self.step_factors(k, link=k > k0):
                graph.add(f)
        return graph

    def values(self, traj, k0: int = 0, k1: int | None = None) -> gtsam.Values:
        """gtsam Values of a :class:`Trajectory` for steps ``k0 .. k1-1``."""
        k1 = self.prob.n if k1 is None else k1
        values = gtsam.Values()
        for k in range(k0, k1):
            gf.insert_state(values, k, traj.R[k], traj.q[k], traj.W[k], self.contacts(k))
        return values
