"""Nonlinear single-track vehicle model with magic-formula tyres, load transfer and friction mu.

States (vehicle frame at the COG, x forward, y left; world frame x east, y north):
``v_x`` [m/s], ``v_y`` [m/s], ``r`` yaw rate [rad/s, ccw], ``x``/``y`` [m], ``psi``
[rad, ccw from east]. Inputs: front wheel steer angle ``delta`` [rad] and the driver's
longitudinal acceleration demand [m/s^2], turned into drive forces (front-, rear- or
all-wheel drive: :attr:`VehicleParams.drivetrain`) or brake forces (front/rear split)
and limited per wheel by the friction ellipse (traction control / ABS).

Per wheel (fl, fr, rl, rr) the normal load includes longitudinal and lateral load
transfer (from the previous step's accelerations); the lateral force is a Pacejka
magic formula scaled by the load-sensitive friction ``mu_i Fz_i``, reduced by the
longitudinal force (friction ellipse). Below ~3 m/s the lateral dynamics blend into
the kinematic model (slip angles are ill-defined near standstill).

Integration: Heun (RK2) at :data:`INTERNAL_RATE_HZ`; samples every 50 Hz. The loop is
plain Python floats (``math``) because that is several times faster than NumPy scalars.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from prml2_edge import schema

INTERNAL_RATE_HZ = 100.0
STEPS_PER_SAMPLE = int(round(INTERNAL_RATE_HZ / schema.SAMPLE_RATE_HZ))


@dataclass(frozen=True)
class VehicleParams:
    """A compact front-wheel-drive passenger car (values typical of a C/D-segment sedan)."""

    mass_kg: float = 1550.0
    yaw_inertia_kgm2: float = 2500.0
    lf_m: float = 1.20  # COG to front axle
    lr_m: float = 1.55  # COG to rear axle
    track_m: float = 1.56  # track width (both axles)
    cog_height_m: float = 0.55
    front_roll_share: float = 0.55  # share of lateral load transfer taken by the front axle
    steering_ratio: float = 15.5  # steering wheel angle / front wheel angle
    max_wheel_angle_rad: float = 0.58  # ~ 515 deg at the steering wheel
    wheel_radius_m: float = 0.32
    # tyres (per wheel): cornering stiffness at nominal load and mu = 1, magic-formula shape
    cornering_stiffness_front_npr: float = 52000.0  # N/rad
    cornering_stiffness_rear_npr: float = 60000.0  # N/rad
    mf_c_lat: float = 1.3
    mf_e_lat: float = -0.6
    load_sensitivity: float = 0.12  # mu drop per unit relative load increase
    mf_b_long: float = 13.0  # longitudinal slip stiffness factor (dry)
    mf_c_long: float = 1.6
    brake_front_share: float = 0.66
    brake_gain_n_per_bar: float = 160.0  # total braking force per bar master cylinder pressure
    drag_coeff_n_per_m2s2: float = 0.40  # 0.5 rho Cd A
    rolling_coeff: float = 0.012
    engine_brake_n: float = 250.0  # coasting force before the brakes are used
    drivetrain: str = "fwd"  # "fwd", "rwd" or "awd" (drive and engine-brake force split by drive_front_share)
    awd_front_share: float = 0.6  # AWD: share of the drive force on the front axle

    def __post_init__(self) -> None:
        if self.drivetrain not in ("fwd", "rwd", "awd"):
            raise ValueError(f"drivetrain must be 'fwd', 'rwd' or 'awd', got {self.drivetrain!r}")

    @property
    def drive_front_share(self) -> float:
        """Share of the drive (and engine-brake) force on the front axle."""
        return {"fwd": 1.0, "rwd": 0.0, "awd": self.awd_front_share}[self.drivetrain]

    @property
    def wheelbase_m(self) -> float:
        return self.lf_m + self.lr_m


@dataclass
class VehicleTrace:
    """50 Hz samples of the simulated vehicle (all arrays (N,), SI)."""

    v_x: np.ndarray
    v_y: np.ndarray
    r: np.ndarray
    a_x: np.ndarray  # measured-acceleration convention: dv_x/dt - r v_y
    a_y: np.ndarray  # dv_y/dt + r v_x
    x: np.ndarray
    y: np.ndarray
    psi: np.ndarray
    delta: np.ndarray  # front wheel angle [rad]
    fx_front_n: np.ndarray  # per-axle longitudinal tyre force [N] (sum of both wheels)
    fx_rear_n: np.ndarray
    fz_n: np.ndarray  # (N, 4) normal loads fl, fr, rl, rr [N]
    brake_force_n: np.ndarray  # total commanded braking force [N] (>= 0)
    mu: float


def simulate_vehicle(params: VehicleParams, mu: float, delta_cmd: np.ndarray, accel_cmd: np.ndarray,
                     v_ref: np.ndarray, psi0_rad: float = 0.0, home_radius_m: float = 700.0,
                     free_steer: np.ndarray | None = None, progress_cb=None, v0_mps: float = 0.0) -> VehicleTrace:
    """Run the closed loop (speed controller + vehicle) over the driver's 50 Hz plan.

    Parameters
    ----------
    params : VehicleParams
    mu : float
        Tyre-road friction coefficient (1.0 dry asphalt, 0.2-0.5 snow).
    delta_cmd : ndarray (N,)
        Front wheel angle demanded by the driver [rad] (already rate limited).
    accel_cmd : ndarray (N,)
        Feed-forward longitudinal acceleration of the plan [m/s^2].
    v_ref : ndarray (N,)
        Planned speed [m/s]; a proportional term tracks it.
    psi0_rad : float
        Initial heading, ccw from east.
    home_radius_m : float
        Beyond this distance from the origin, ``free_steer`` samples get a gentle
        curvature towards the origin (the test track's extent).
    free_steer : ndarray (N,) bool, optional
        Samples where the driver may add the steer-home correction.
    progress_cb : callable, optional
        Called with the number of 50 Hz samples done, every 500 samples.
    v0_mps : float
        Speed at the start (0: from rest), straight ahead.
    """
    p = params
    n = len(delta_cmd)
    m, L, g, d_max = p.mass_kg, p.wheelbase_m, schema.G_MPS2, p.max_wheel_angle_rad
    forces, deriv = _dynamics(p, mu)
    free = np.ones(n, dtype=bool) if free_steer is None else free_steer

    out = np.zeros((n, 16))
    vx, vy, r, x, y, psi = float(v0_mps), 0.0, 0.0, 0.0, 0.0, psi0_rad
    ax_prev, ay_prev = 0.0, 0.0
    delta = 0.0
    kp_speed = 0.9  # 1/s
    for k in range(n):
        # driver: speed tracking on top of the plan's feed-forward
        vr = float(v_ref[k])
        ax_dem = float(accel_cmd[k]) + kp_speed * (vr - vx)
        delta = float(delta_cmd[k])
        if free[k] and vx > 3.0:
            delta = _steer_home(delta, vx, x, y, psi, home_radius_m, L)
        delta = max(-d_max, min(d_max, delta))
        vx, vy, r, x, y, psi, ax_prev, ay_prev = _integrate_sample(deriv, vx, vy, r, x, y, psi, ax_prev, ay_prev,
                                                                   delta, ax_dem)
        ax, ay, _, fx_f, fx_r, fz, brake = forces(vx, vy, r, delta, ax_dem, ax_prev, ay_prev)
        if vx == 0.0 and ax_dem <= 0.05:
            ax = ay = 0.0
            fx_f = fx_r = 0.0
            brake = max(brake, 0.3 * m * g)  # driver holds the car on the brake
        out[k] = (vx, vy, r, ax, ay, x, y, psi, delta, fx_f, fx_r, fz[0], fz[1], fz[2], fz[3], brake)
        if progress_cb is not None and k % 500 == 499:
            progress_cb(500)
    if progress_cb is not None:
        progress_cb(n % 500)
    return VehicleTrace(
        v_x=out[:, 0], v_y=out[:, 1], r=out[:, 2], a_x=out[:, 3], a_y=out[:, 4], x=out[:, 5], y=out[:, 6],
        psi=out[:, 7], delta=out[:, 8], fx_front_n=out[:, 9], fx_rear_n=out[:, 10], fz_n=out[:, 11:15],
        brake_force_n=out[:, 15], mu=mu,
    )


def _steer_home(delta: float, vx: float, x: float, y: float, psi: float, home_radius_m: float, L: float) -> float:
    """The driver's wheel angle plus a gentle curvature towards the origin beyond ``home_radius_m``."""
    k_home = 0.004  # 1/m per rad of heading error
    dist = math.hypot(x, y)
    if dist > home_radius_m:
        err = math.atan2(-y, -x) - psi
        err = math.atan2(math.sin(err), math.cos(err))
        k_max = 1.5 / (vx * vx)  # at most 1.5 m/s^2 of lateral acceleration
        kappa = max(-k_max, min(k_max, k_home * err * min(1.0, (dist - home_radius_m) / 200.0)))
        delta += math.atan(L * kappa)
    return delta


def _integrate_sample(deriv, vx, vy, r, x, y, psi, ax_prev, ay_prev, delta, ax_dem):
    """Heun steps over one 50 Hz sample; returns the new ``(vx, vy, r, x, y, psi, ax_prev, ay_prev)``.

    A car at rest with no drive demand stays at rest (the brakes hold it; no reversing).
    """
    dt = 1.0 / INTERNAL_RATE_HZ
    for _ in range(STEPS_PER_SAMPLE):
        if vx <= 0.0 and ax_dem <= 0.05:
            return 0.0, 0.0, 0.0, x, y, psi, 0.0, 0.0
        k1 = deriv(vx, vy, r, psi, delta, ax_dem, ax_prev, ay_prev)
        s1 = (vx + dt * k1[0], vy + dt * k1[1], r + dt * k1[2], psi + dt * k1[5])
        k2 = deriv(s1[0], s1[1], s1[2], s1[3], delta, ax_dem, ax_prev, ay_prev)
        h2 = 0.5 * dt
        vx += h2 * (k1[0] + k2[0])
        vy += h2 * (k1[1] + k2[1])
        r += h2 * (k1[2] + k2[2])
        x += h2 * (k1[3] + k2[3])
        y += h2 * (k1[4] + k2[4])
        psi += h2 * (k1[5] + k2[5])
        if vx < 0.0:  # brakes hold the car; no reversing
            vx, vy, r = 0.0, 0.0, 0.0
        ax_prev = 0.5 * (k1[0] + k2[0]) - r * vy
        ay_prev = 0.5 * (k1[1] + k2[1]) + r * vx
    return vx, vy, r, x, y, psi, ax_prev, ay_prev


def _axle_constants(p: VehicleParams, mu: float) -> tuple[float, float, float, float, float, float]:
    """Static wheel loads front/rear [N], magic-formula B front/rear, lateral load transfer per m/s^2 front/rear."""
    m, lf, lr, L, h = p.mass_kg, p.lf_m, p.lr_m, p.wheelbase_m, p.cog_height_m
    g = schema.G_MPS2
    fz0_f = m * g * lr / L / 2.0
    fz0_r = m * g * lf / L / 2.0
    # magic-formula B from the cornering stiffness; lower mu also softens the tyre a little
    stiff_scale = 0.45 + 0.55 * min(mu, 1.0)
    b_f = p.cornering_stiffness_front_npr * stiff_scale / (p.mf_c_lat * mu * fz0_f)
    b_r = p.cornering_stiffness_rear_npr * stiff_scale / (p.mf_c_lat * mu * fz0_r)
    tw = p.track_m
    ks_f = p.front_roll_share * m * h / tw
    ks_r = (1.0 - p.front_roll_share) * m * h / tw
    return fz0_f, fz0_r, b_f, b_r, ks_f, ks_r


def _dynamics(p: VehicleParams, mu: float):
    """The single-track model of ``p`` on friction ``mu``: ``(forces, deriv)``.

    ``forces(vx, vy, r, delta, ax_dem, ax_prev, ay_prev)`` gives ``(a_x, a_y, r_dot, fx_front, fx_rear,
    fz (fl, fr, rl, rr), brake)``; ``deriv(vx, vy, r, psi, delta, ax_dem, ax_prev, ay_prev)`` the time
    derivatives of ``(vx, vy, r, x, y, psi)``. ``ax_prev``/``ay_prev`` are the previous step's
    accelerations (load transfer).
    """
    m, iz, lf, lr, L = p.mass_kg, p.yaw_inertia_kgm2, p.lf_m, p.lr_m, p.wheelbase_m
    g = schema.G_MPS2
    h = p.cog_height_m
    fz0_f, fz0_r, b_f, b_r, ks_f, ks_r = _axle_constants(p, mu)
    c_lat, e_lat, ls = p.mf_c_lat, p.mf_e_lat, p.load_sensitivity
    drive_f = p.drive_front_share

    def wheel_fy(alpha: float, fz: float, fx: float, b: float, fz0: float) -> float:
        mu_i = mu * (1.0 - ls * (fz - fz0) / fz0)
        fmax2 = (mu_i * fz) ** 2 - fx * fx
        if fmax2 <= 0.0:
            return 0.0
        ba = b * alpha
        return math.sqrt(fmax2) * math.sin(c_lat * math.atan(ba - e_lat * (ba - math.atan(ba))))

    def forces(vx, vy, r, delta, ax_dem, ax_prev, ay_prev):
        # normal loads from the previous accelerations (clamped: no wheel lift modelling)
        fzf = fz0_f - m * ax_prev * h / L / 2.0
        fzr = fz0_r + m * ax_prev * h / L / 2.0
        dlf = ks_f * ay_prev
        dlr = ks_r * ay_prev
        fz_fl = max(fzf - dlf, 150.0)
        fz_fr = max(fzf + dlf, 150.0)
        fz_rl = max(fzr - dlr, 150.0)
        fz_rr = max(fzr + dlr, 150.0)
        # longitudinal demand -> axle forces, limited by friction (TCS/ABS at 95 %)
        resist = p.drag_coeff_n_per_m2s2 * vx * vx + (p.rolling_coeff * m * g if vx > 0.05 else 0.0)
        f_dem = m * ax_dem + resist
        brake = 0.0
        if f_dem >= 0.0:
            fx_f = drive_f * f_dem
            fx_r = (1.0 - drive_f) * f_dem
        else:
            brake = max(0.0, -f_dem - p.engine_brake_n)
            eng = min(-f_dem, p.engine_brake_n)
            fx_f = -drive_f * eng - p.brake_front_share * brake
            fx_r = -(1.0 - drive_f) * eng - (1.0 - p.brake_front_share) * brake
        lim_f = 0.95 * mu * (fz_fl + fz_fr)
        lim_r = 0.95 * mu * (fz_rl + fz_rr)
        fx_f = max(-lim_f, min(lim_f, fx_f))
        fx_r = max(-lim_r, min(lim_r, fx_r))
        # slip angles (vx floored: the kinematic blend takes over at low speed)
        vxe = max(vx, 1.0)
        a_f = delta - math.atan2(vy + lf * r, vxe)
        a_r = -math.atan2(vy - lr * r, vxe)
        fy_f = wheel_fy(a_f, fz_fl, 0.5 * fx_f, b_f, fz0_f) + wheel_fy(a_f, fz_fr, 0.5 * fx_f, b_f, fz0_f)
        fy_r = wheel_fy(a_r, fz_rl, 0.5 * fx_r, b_r, fz0_r) + wheel_fy(a_r, fz_rr, 0.5 * fx_r, b_r, fz0_r)
        cd, sd = math.cos(delta), math.sin(delta)
        fxv = fx_f * cd - fy_f * sd + fx_r - resist
        fyv = fx_f * sd + fy_f * cd + fy_r
        mz = lf * (fx_f * sd + fy_f * cd) - lr * fy_r
        return fxv / m, fyv / m, mz / iz, fx_f, fx_r, (fz_fl, fz_fr, fz_rl, fz_rr), brake

    def deriv(vx, vy, r, psi, delta, ax_dem, ax_prev, ay_prev):
        ax, ay, rdot_dyn, *_ = forces(vx, vy, r, delta, ax_dem, ax_prev, ay_prev)
        dvx = ax + r * vy
        dvy_dyn = ay - r * vx
        # kinematic blend below 3 m/s: relax v_y and r towards the kinematic single track
        w = min(max((vx - 1.0) / 2.0, 0.0), 1.0)
        if w < 1.0:
            r_kin = vx * math.tan(delta) / L
            vy_kin = lr * r_kin
            dvy = w * dvy_dyn + (1.0 - w) * (vy_kin - vy) / 0.05
            rdot = w * rdot_dyn + (1.0 - w) * (r_kin - r) / 0.05
        else:
            dvy, rdot = dvy_dyn, rdot_dyn
        c, s = math.cos(psi), math.sin(psi)
        return dvx, dvy, rdot, vx * c - vy * s, vx * s + vy * c, r

    return forces, deriv
