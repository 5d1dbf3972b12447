"""Motor, load and position-controller parameters of the simulated drive (seed 000 chapter 7).

Regulation (seed 000 7.2/7.3): a PID position controller at 1 ms feeding a PI current loop an order of
magnitude faster, so the current is taken equal to its reference, limited. Mechanics: inertia J, viscous
r*w and Coulomb r0*sign(w) friction, torque k_M * i; no feedforward (7.3.4: none in IPM). Controller
(7.3.3): C(s) = Kp + Ki/s + Kd*s / (1 + Kd/(16*Kp) * s), EPOS gains converted with the seed's factors.
`LoopConstants` is the per-tick arithmetic in counts, counts/ms and A: exact zero-order-hold plant
over a tick, backward-Euler derivative filter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

TS_S = 0.001  # position loop sampling period (seed 000 7.3.3)

# seed 000 7.3.3 conversion factors, EPOS units -> SI
POS_KP_SI = 10e-3  # A/rad per unit
POS_KI_SI = 78e-3  # A/(s*rad) per unit
POS_KD_SI = 80e-6  # A*s/rad per unit


@dataclass(frozen=True)
class MotorParams:
    """Plant and position-controller parameters, SI units, referred to the motor shaft."""

    name: str
    inertia_kgm2: float  # J = J_motor + J_load
    torque_constant_nm_per_a: float  # k_M
    viscous_friction_nm_s: float  # r (Nm per rad/s)
    coulomb_friction_nm: float  # r0
    current_limit_a: float  # output current limit
    kp_a_per_rad: float
    ki_a_per_rad_s: float
    kd_a_s_per_rad: float

    def __post_init__(self) -> None:
        for name in ("inertia_kgm2", "torque_constant_nm_per_a", "current_limit_a", "kp_a_per_rad"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"motor {self.name!r}: {name} must be finite and > 0, got {v}")
        for name in ("viscous_friction_nm_s", "coulomb_friction_nm", "ki_a_per_rad_s", "kd_a_s_per_rad"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"motor {self.name!r}: {name} must be finite and >= 0, got {v}")

    @classmethod
    def from_epos_gains(cls, name: str, *, inertia_gcm2: float, torque_constant_mnm_per_a: float,
                        viscous_friction_unm_s: float, coulomb_friction_mnm: float, current_limit_a: float,
                        kp: int, ki: int, kd: int) -> MotorParams:
        """Build from the units the seed prints (g*cm^2, mNm/A, uNm/(rad/s), mNm, EPOS gain values)."""
        return cls(
            name=name,
            inertia_kgm2=inertia_gcm2 * 1e-7,
            torque_constant_nm_per_a=torque_constant_mnm_per_a * 1e-3,
            viscous_friction_nm_s=viscous_friction_unm_s * 1e-6,
            coulomb_friction_nm=coulomb_friction_mnm * 1e-3,
            current_limit_a=current_limit_a,
            kp_a_per_rad=kp * POS_KP_SI,
            ki_a_per_rad_s=ki * POS_KI_SI,
            kd_a_s_per_rad=kd * POS_KD_SI,
        )


# Seed 000 7.6.1, Example 1: EC 40 with a 5000 g*cm^2 fly wheel (high inertia, low friction).
# Position gains 1120 / 812 / 8244 -> 11.2 A/rad, 63.2 A/(s*rad), 0.660 A*s/rad. Current limit
# = 2 x nominal current 3.4 A (EPOS default output current limit = 2 x continuous current).
EC40_FLYWHEEL = MotorParams.from_epos_gains(
    "EC 40 + fly wheel (seed 000 7.6.1)",
    inertia_gcm2=85 + 5000, torque_constant_mnm_per_a=38.2, viscous_friction_unm_s=9.05,
    coulomb_friction_mnm=0.0, current_limit_a=6.8, kp=1120, ki=812, kd=8244,
)

# Seed 000 7.6.2, Example 2: RE 35 on a linear drive (low inertia, high friction).
# Friction M_r = 211 uNm/(rad/s) * w + 8.65 mNm * sign(w), plus the motor's own 6 uNm/(rad/s) -> r1 = 217.
# Position gains 386 / 1193 / 616. Current limit = 2 x nominal 1.95 A.
RE35_LINEAR = MotorParams.from_epos_gains(
    "RE 35 + linear drive (seed 000 7.6.2)",
    inertia_gcm2=72 + 100, torque_constant_mnm_per_a=52.5, viscous_friction_unm_s=217.0,
    coulomb_friction_mnm=8.65, current_limit_a=3.9, kp=386, ki=1193, kd=616,
)

PRESETS: dict[str, MotorParams] = {"ec40": EC40_FLYWHEEL, "re35": RE35_LINEAR}
DEFAULT_MOTOR = RE35_LINEAR


@dataclass(frozen=True)
class LoopConstants:
    """Per-tick coefficients in drive units: counts, counts/ms, A; one tick = 1 ms.

        e      = demand - position                                  (counts)
        integ  = clamp(integ + ki * e, +-i_max)                      (A)
        dterm  = kd_f * dterm + kd_g * (e - e_prev)                  (A)
        i      = clamp(kp * e + integ + dterm, +-i_max)              (A)
        i_eff  = i minus the Coulomb friction current (opposing motion, sticking at rest)
        pos   += psi * vel + eta * i_eff
        vel    = phi * vel + gam * i_eff
    """

    kp: float
    ki: float
    kd_f: float
    kd_g: float
    i_max: float
    coulomb_a: float
    phi: float
    gam: float
    psi: float
    eta: float
    counts_per_rev: int

    @classmethod
    def build(cls, motor: MotorParams, counts_per_rev: int) -> LoopConstants:
        if counts_per_rev <= 0:
            raise ValueError(f"counts_per_rev must be > 0, got {counts_per_rev}")
        rad_per_count = 2.0 * math.pi / counts_per_rev
        h = TS_S
        phi, gam, psi, eta = plant_constants(motor, counts_per_rev, h)
        # controller
        kp = motor.kp_a_per_rad * rad_per_count
        ki = motor.ki_a_per_rad_s * h * rad_per_count
        if motor.kd_a_s_per_rad > 0.0:
            tau = motor.kd_a_s_per_rad / (16.0 * motor.kp_a_per_rad)
            kd_f = tau / (tau + h)
            kd_g = motor.kd_a_s_per_rad / (tau + h) * rad_per_count
        else:
            kd_f = 0.0
            kd_g = 0.0
        return cls(kp=kp, ki=ki, kd_f=kd_f, kd_g=kd_g, i_max=motor.current_limit_a,
                   coulomb_a=motor.coulomb_friction_nm / motor.torque_constant_nm_per_a, phi=phi, gam=gam, psi=psi,
                   eta=eta, counts_per_rev=counts_per_rev)


def plant_constants(motor: MotorParams, counts_per_rev: int, h_s: float) -> tuple[float, float, float, float]:
    """(phi, gam, psi, eta) of the plant over a step of `h_s` seconds with the current held (exact
    zero-order hold of J*dw/dt = k_M*i - r*w), in the model's units (counts, counts/ms, A):
    vel' = phi*vel + gam*i, pos' = pos + psi*vel + eta*i. `LoopConstants` uses the 1 ms tick; the data
    recorder's sub-steps (bus/sim/data_recorder.py) use its sampling period when that is finer."""
    if counts_per_rev <= 0:
        raise ValueError(f"counts_per_rev must be > 0, got {counts_per_rev}")
    if not (math.isfinite(h_s) and h_s > 0.0):
        raise ValueError(f"plant step must be > 0 s, got {h_s}")
    counts_per_rad = 1.0 / (2.0 * math.pi / counts_per_rev)  # as LoopConstants always computed it (bit-identical)
    h = h_s
    j = motor.inertia_kgm2
    km = motor.torque_constant_nm_per_a
    r = motor.viscous_friction_nm_s
    if r > 0.0:
        a = r / j
        phi = math.exp(-a * h)
        one_minus = -math.expm1(-a * h)
        w_per_a = km * one_minus / r  # rad/s per A after one step
        th_from_w = one_minus / a  # rad per rad/s
        th_per_a = km * (h - one_minus / a) / r  # rad per A
    else:
        phi = 1.0
        w_per_a = km * h / j
        th_from_w = h
        th_per_a = km * h * h / (2.0 * j)
    # velocity state in counts/ms: w [rad/s] = vel * counts->rad * 1000
    vel_scale = counts_per_rad / 1000.0  # (counts/ms) per (rad/s)
    gam = w_per_a * vel_scale
    psi = th_from_w * 1000.0  # counts per (counts/ms): th = w*th_from_w, w = vel*1000/counts_per_rad
    eta = th_per_a * counts_per_rad
    return phi, gam, psi, eta
