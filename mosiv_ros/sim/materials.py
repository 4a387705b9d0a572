"""Material families, their parameters, and their constitutive models as Warp functions.

Every particle carries the elastic left Cauchy-Green tensor ``b = F_e F_e^T`` instead of the
deformation gradient F. All four families below need only ``b`` (isotropic hyperelasticity and
isotropic plasticity), so no SVD is taken anywhere: the return mappings are closed-form in the
deviatoric part of ``b``, and gradients stay finite at rest, where an SVD's adjoint is singular
(F = I has three equal singular values). The per-substep update is ``b <- f b f^T`` with the
incremental deformation ``f = I + dt C`` (C is the MLS-MPM affine velocity field), followed by
the family's return mapping.

Families (``FAMILY_CODES``) and their parameters (per object, SI units):

- elastic: compressible neo-Hookean, E, nu, density (Bonet & Wood 2008, Eq. 6.28).
- plastic: von Mises (J2) plasticity on the isochoric part of b, E, nu, yield_stress
  (Simo & Hughes 1998, Box 9.1; Simo 1988). Models plasticine and metal-like behaviour.
- sand: Drucker-Prager, E, nu, friction_angle, with the projection rules of Klar et al. 2016
  (Sec. 7.3: tension -> stress-free tip, cone violation -> scale the deviatoric stress onto the
  cone), written on the Kirchhoff stress of the same b-based model instead of Hencky strain.
- fluid: weakly compressible Newtonian, bulk_modulus, viscosity (Tait equation of state,
  Becker & Teschner 2007, gamma = 7; Newtonian viscous stress on the MLS-MPM velocity gradient).

Every object also has a Coulomb ``friction`` coefficient for object-object contact, combined
per pair with the symmetric rule mu_kl = (mu_k + mu_l) / 2 (MOSIV).

What it is not for: grid transfers (``kernels``) or external forces (``effects``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import warp as wp

from mosiv_ros.sim.params import ParamSpec

FAMILY_CODES = {"elastic": 0, "plastic": 1, "sand": 2, "fluid": 3}
ELASTIC = wp.constant(0)
PLASTIC = wp.constant(1)
SAND = wp.constant(2)
FLUID = wp.constant(3)
TAIT_GAMMA = wp.constant(7.0)

SOLIDS = ("elastic", "plastic", "sand")
ALL = tuple(FAMILY_CODES)

MATERIAL_PARAMS = (
    ParamSpec("E", 1.0e5, 1.0e2, 1.0e10, "Pa", "Young's modulus", True, families=SOLIDS),
    ParamSpec("nu", 0.3, 0.0, 0.49, "", "Poisson's ratio", True, families=SOLIDS),
    ParamSpec("density", 1000.0, 1.0, 2.0e4, "kg/m^3", "mass density", True, families=ALL),
    ParamSpec("yield_stress", 1.0e4, 1.0, 1.0e9, "Pa", "von Mises yield stress", True,
              families=("plastic",)),
    ParamSpec("friction_angle", math.radians(30.0), 0.0, math.radians(60.0), "rad",
              "Drucker-Prager friction angle", True, families=("sand",)),
    ParamSpec("bulk_modulus", 2.0e5, 1.0e2, 1.0e10, "Pa", "fluid bulk modulus", True,
              families=("fluid",)),
    ParamSpec("viscosity", 1.0, 0.0, 1.0e5, "Pa*s", "fluid dynamic viscosity", True,
              families=("fluid",)),
    ParamSpec("friction", 0.3, 0.0, 5.0, "", "Coulomb coefficient for contact with other objects",
              True, families=ALL),
)
MATERIAL_PARAM_NAMES = tuple(spec.name for spec in MATERIAL_PARAMS)

FRICTION_ANGLE_DEG = "friction_angle_deg"
"""A friction angle as users give it, in degrees (the simulator's ``friction_angle`` is radians)."""


def in_sim_units(params: Mapping[str, float]) -> dict[str, float]:
    """User-facing material parameters in the simulator's names and units.

    A friction angle given as ``friction_angle_deg`` (degrees) becomes ``friction_angle`` (rad).
    """
    known = dict(params)
    if FRICTION_ANGLE_DEG in known:
        known["friction_angle"] = float(np.radians(known.pop(FRICTION_ANGLE_DEG)))
    return known


FAMILY_PARAMS = {
    "elastic": ("E", "nu", "density", "friction"),
    "plastic": ("E", "nu", "yield_stress", "density", "friction"),
    "sand": ("E", "nu", "friction_angle", "density", "friction"),
    "fluid": ("bulk_modulus", "viscosity", "density", "friction"),
}
"""The parameters each family uses (the others are stored but have no effect)."""


def wave_speed(family: str, values: dict[str, np.ndarray]) -> np.ndarray:
    """Largest elastic (P-wave) or acoustic speed, m/s, of one object over the batch.

    ``values`` maps parameter name to that object's values over the batch. Used for the CFL
    time-step bound.
    """
    rho = values["density"]
    if family == "fluid":
        return np.sqrt(values["bulk_modulus"] / rho)
    E, nu = values["E"], values["nu"]
    p_modulus = E * (1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu))  # lambda + 2 mu
    return np.sqrt(p_modulus / rho)


@wp.func
def lame_mu(E: float, nu: float):
    return E / (2.0 * (1.0 + nu))


@wp.func
def lame_lambda(E: float, nu: float):
    return E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


@wp.func
def isochoric_split(b: wp.mat33, J: float):
    """Isochoric part b_bar = J^(-2/3) b of b."""
    return b * wp.pow(J, -2.0 / 3.0)


@wp.func
def deviator(a: wp.mat33):
    return a - wp.identity(n=3, dtype=float) * (wp.trace(a) / 3.0)


@wp.func
def von_mises_return(b: wp.mat33, mu: float, yield_stress: float):
    """Radial return of s = mu dev(b_bar) onto ||s|| = sqrt(2/3) sigma_y (Simo & Hughes Box 9.1).

    Volume (J) and the mean of b_bar are kept; only the deviatoric part shrinks.
    """
    J = wp.sqrt(wp.determinant(b))
    b_bar = isochoric_split(b, J)
    mean = wp.trace(b_bar) / 3.0
    s = mu * deviator(b_bar)
    s_sq = wp.ddot(s, s)  # squared: sqrt's adjoint is infinite at s = 0, even off this branch
    limit = wp.sqrt(2.0 / 3.0) * yield_stress
    result = b
    if s_sq > limit * limit:
        s_new = s * (limit / wp.sqrt(s_sq))
        b_bar_new = s_new / mu + wp.identity(n=3, dtype=float) * mean
        result = b_bar_new * wp.pow(J, 2.0 / 3.0)
    return result


@wp.func
def drucker_prager_return(b: wp.mat33, mu: float, kappa: float, friction_angle: float):
    """Drucker-Prager projection (Klar et al. 2016, Sec. 7.3) on the Kirchhoff stress.

    Mean Kirchhoff stress p = kappa/2 (J^2 - 1) (tension positive) and deviator
    s = mu dev(b_bar). Tension (p >= 0): project to the stress-free tip, b = I. Otherwise the cone
    ||s|| <= -3 alpha p, alpha = sqrt(2/3) 2 sin(phi) / (3 - sin(phi)) (Klar Eq. 27's alpha in
    stress form), is enforced by scaling s, keeping p.
    """
    J = wp.sqrt(wp.determinant(b))
    p = 0.5 * kappa * (J * J - 1.0)
    result = b
    if p >= 0.0:
        result = wp.identity(n=3, dtype=float)
    else:
        sin_phi = wp.sin(friction_angle)
        alpha = wp.sqrt(2.0 / 3.0) * 2.0 * sin_phi / (3.0 - sin_phi)
        b_bar = isochoric_split(b, J)
        mean = wp.trace(b_bar) / 3.0
        s = mu * deviator(b_bar)
        s_sq = wp.ddot(s, s)
        limit = -3.0 * alpha * p
        if s_sq > limit * limit:
            s_new = s * (limit / wp.sqrt(s_sq))
            b_bar_new = s_new / mu + wp.identity(n=3, dtype=float) * mean
            result = b_bar_new * wp.pow(J, 2.0 / 3.0)
    return result


@wp.func
def return_mapping(
    family: int, b: wp.mat33, E: float, nu: float, yield_stress: float, friction_angle: float
):
    """The family's plastic correction of the trial b (elastic: none; fluid: keep only J)."""
    result = b
    if family == PLASTIC:
        result = von_mises_return(b, lame_mu(E, nu), yield_stress)
    elif family == SAND:
        mu = lame_mu(E, nu)
        kappa = lame_lambda(E, nu) + 2.0 / 3.0 * mu
        result = drucker_prager_return(b, mu, kappa, friction_angle)
    elif family == FLUID:
        # A fluid keeps no shape: b = J^(2/3) I, J = sqrt(det b).
        J = wp.sqrt(wp.determinant(b))
        result = wp.identity(n=3, dtype=float) * wp.pow(J, 2.0 / 3.0)
    return result


@wp.func
def kirchhoff_stress(
    family: int,
    b: wp.mat33,
    C: wp.mat33,
    E: float,
    nu: float,
    bulk_modulus: float,
    viscosity: float,
):
    """Kirchhoff stress tau = J sigma of one particle.

    elastic: tau = mu (b - I) + lambda ln(J) I (neo-Hookean, Bonet & Wood Eq. 6.28);
    plastic, sand: tau = kappa/2 (J^2 - 1) I + mu dev(b_bar) (Simo & Hughes Eq. 9.2.6);
    fluid: tau = -J p I + J eta (C + C^T - 2/3 tr(C) I), p = K (J^-gamma - 1) / gamma.
    """
    I = wp.identity(n=3, dtype=float)
    J = wp.sqrt(wp.determinant(b))
    tau = wp.mat33(0.0)
    if family == FLUID:
        pressure = bulk_modulus * (wp.pow(J, -TAIT_GAMMA) - 1.0) / TAIT_GAMMA
        strain_rate = C + wp.transpose(C) - I * (2.0 / 3.0 * wp.trace(C))
        tau = I * (-J * pressure) + strain_rate * (J * viscosity)
    elif family == ELASTIC:
        mu = lame_mu(E, nu)
        tau = (b - I) * mu + I * (lame_lambda(E, nu) * wp.log(J))
    else:
        mu = lame_mu(E, nu)
        kappa = lame_lambda(E, nu) + 2.0 / 3.0 * mu
        tau = I * (0.5 * kappa * (J * J - 1.0)) + deviator(isochoric_split(b, J)) * mu
    return tau


# The adjoints of the particle's update, written out for P2G's written adjoint
# (``kernels.p2g_adjoint_kernel``): each takes the same inputs as its function and the adjoint of its
# result, and returns the adjoints of its inputs. Where a function branches, the adjoint takes
# the branch the function takes, computed by the same expressions. The two radial returns
# below are written in the closed form their branch equals: with n = |dev(b)|, both set
# b <- r dev(b) + tr(b) / 3 I, r = limit J^(2/3) / (mu n).


@wp.func
def lame_adjoint(E: float, nu: float, adj_mu: float, adj_lambda: float):
    """The adjoints of E and nu, given those of ``lame_mu`` and ``lame_lambda``."""
    one_nu = 1.0 + nu
    d = one_nu * (1.0 - 2.0 * nu)
    return (adj_mu / (2.0 * one_nu) + adj_lambda * nu / d,
            -adj_mu * E / (2.0 * one_nu * one_nu) + adj_lambda * E * (1.0 + 2.0 * nu * nu) / (d * d))


@wp.func
def radial_return_adjoint(b: wp.mat33, r: float, adj: wp.mat33):
    """(adj_b, adj_r) of r dev(b) + tr(b) / 3 I with r fixed, given the adjoint ``adj`` of the result."""
    adj_dev = deviator(adj)
    return adj_dev * r + wp.identity(n=3, dtype=float) * (wp.trace(adj) / 3.0), wp.ddot(adj_dev, b)


@wp.func
def return_mapping_adjoint(family: int, b: wp.mat33, E: float, nu: float, yield_stress: float,
                           friction_angle: float, adj: wp.mat33):
    """(adj_b, adj_mu, adj_lambda, adj_yield_stress, adj_friction_angle) of ``return_mapping``.

    ``b`` is its trial b and ``adj`` the adjoint of its result; mu and lambda are E and nu's
    Lame parameters (``lame_adjoint``).
    """
    adj_b = adj
    adj_mu = float(0.0)
    adj_lambda = float(0.0)
    adj_yield = float(0.0)
    adj_angle = float(0.0)
    if family == FLUID:  # b' = det(b)^(1/3) I
        adj_b = wp.transpose(wp.inverse(b)) * (wp.trace(adj) / 3.0 * wp.pow(wp.determinant(b), 1.0 / 3.0))
    elif family == PLASTIC or family == SAND:
        mu = lame_mu(E, nu)
        kappa = lame_lambda(E, nu) + 2.0 / 3.0 * mu
        J = wp.sqrt(wp.determinant(b))
        limit = wp.sqrt(2.0 / 3.0) * yield_stress
        p = 0.5 * kappa * (J * J - 1.0)
        sin_phi = wp.sin(friction_angle)
        alpha = wp.sqrt(2.0 / 3.0) * 2.0 * sin_phi / (3.0 - sin_phi)
        if family == SAND:
            limit = -3.0 * alpha * p
        s = mu * deviator(isochoric_split(b, J))
        if family == SAND and p >= 0.0:  # the stress-free tip: b' = I
            adj_b = wp.mat33(0.0)
        elif wp.ddot(s, s) > limit * limit:
            dev_b = deviator(b)
            n_sq = wp.ddot(dev_b, dev_b)
            unit = wp.pow(J, 2.0 / 3.0) / (mu * wp.sqrt(n_sq))  # r / limit
            r = limit * unit
            adj_b, adj_r = radial_return_adjoint(b, r, adj)
            # d ln r / db = (1/3) b^-T - dev(b) / n^2, besides the limit's own dependence on b
            inv_t = wp.transpose(wp.inverse(b))
            adj_b = adj_b + (inv_t * (1.0 / 3.0) - dev_b / n_sq) * (adj_r * r)
            adj_mu = -adj_r * r / mu
            adj_limit = adj_r * unit
            if family == PLASTIC:
                adj_yield = adj_limit * wp.sqrt(2.0 / 3.0)
            else:  # limit = -3 alpha p, p = kappa / 2 (det b - 1)
                adj_p = -3.0 * alpha * adj_limit
                adj_b = adj_b + inv_t * (adj_p * 0.5 * kappa * J * J)
                adj_kappa = adj_p * 0.5 * (J * J - 1.0)
                adj_mu += 2.0 / 3.0 * adj_kappa
                adj_lambda = adj_kappa
                three = 3.0 - sin_phi
                adj_angle = -3.0 * p * adj_limit * wp.sqrt(2.0 / 3.0) * 6.0 * wp.cos(friction_angle) / (three * three)
    return adj_b, adj_mu, adj_lambda, adj_yield, adj_angle


@wp.func
def kirchhoff_stress_adjoint(family: int, b: wp.mat33, C: wp.mat33, E: float, nu: float,
                             bulk_modulus: float, viscosity: float, adj: wp.mat33):
    """(adj_b, adj_C, adj_mu, adj_lambda, adj_bulk_modulus, adj_viscosity) of ``kirchhoff_stress``.

    ``adj`` is the adjoint of tau; mu and lambda as in ``return_mapping_adjoint``.
    """
    I = wp.identity(n=3, dtype=float)
    det = wp.determinant(b)
    J = wp.sqrt(det)
    inv_t = wp.transpose(wp.inverse(b))  # d det / db = det b^-T
    tr = wp.trace(adj)
    adj_C = wp.mat33(0.0)
    adj_mu = float(0.0)
    adj_lambda = float(0.0)
    adj_bulk = float(0.0)
    adj_viscosity = float(0.0)
    adj_b = wp.mat33(0.0)
    if family == FLUID:
        # tau = -J p I + J eta S, -J p = -K (J^(1 - gamma) - J) / gamma, S = C + C^T - 2/3 tr(C) I
        power = wp.pow(J, -TAIT_GAMMA)
        strain_rate = C + wp.transpose(C) - I * (2.0 / 3.0 * wp.trace(C))
        adj_S = wp.ddot(adj, strain_rate)
        adj_J = tr * (-bulk_modulus * ((1.0 - TAIT_GAMMA) * power - 1.0) / TAIT_GAMMA) + viscosity * adj_S
        adj_b = inv_t * (adj_J * 0.5 * J)
        adj_bulk = -tr * J * (power - 1.0) / TAIT_GAMMA
        adj_viscosity = J * adj_S
        adj_C = (adj + wp.transpose(adj) - I * (2.0 / 3.0 * tr)) * (J * viscosity)
    elif family == ELASTIC:
        mu = lame_mu(E, nu)
        adj_b = adj * mu + inv_t * (0.5 * lame_lambda(E, nu) * tr)
        adj_mu = wp.ddot(adj, b - I)
        adj_lambda = tr * wp.log(J)
    else:
        # tau = kappa / 2 (det b - 1) I + mu det(b)^(-1/3) dev(b)
        mu = lame_mu(E, nu)
        kappa = lame_lambda(E, nu) + 2.0 / 3.0 * mu
        scale = wp.pow(J, -2.0 / 3.0)
        adj_dev = deviator(adj)
        along = wp.ddot(adj_dev, b)
        adj_b = inv_t * (0.5 * kappa * tr * J * J - mu * along * scale / 3.0) + adj_dev * (mu * scale)
        adj_kappa = 0.5 * (J * J - 1.0) * tr
        adj_mu = scale * along + 2.0 / 3.0 * adj_kappa
        adj_lambda = adj_kappa
    return adj_b, adj_C, adj_mu, adj_lambda, adj_bulk, adj_viscosity
