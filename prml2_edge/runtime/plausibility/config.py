"""The plausibility stage's signal indices and units, and its tunables (:class:`PlausibilityConfig`)."""

from __future__ import annotations

from dataclasses import dataclass

from prml2_edge import schema

_SIG = {s.name: s.index for s in schema.SIGNALS}
VS, SW, YAW, AY, BP = (_SIG[n] for n in ("speedometer_mps", "steering_wheel_angle_rad", "yaw_rate_radps",
                                          "lat_accel_mps2", "brake_pressure_bar"))
FL, FR, RL, RR = schema.WHEEL_SPEED_INDICES
WHEELS = (FL, FR, RL, RR)
N = schema.NUM_SIGNALS
_DEG = schema.DEG_TO_RAD
# the coarsest common step of each signal (the reference car's): a resolution measured online is at most this
COARSEST_STEP = tuple(s.revsted_step for s in schema.SIGNALS)
# (unit, factor from SI) of each signal in the reasons
SIGNAL_UNITS = {VS: ("m/s", 1.0), SW: ("deg", 1 / _DEG), YAW: ("deg/s", 1 / _DEG), AY: ("m/s^2", 1.0),
                BP: ("bar", 1.0), FL: ("m/s", 1.0), FR: ("m/s", 1.0), RL: ("m/s", 1.0), RR: ("m/s", 1.0)}


@dataclass(frozen=True)
class PlausibilityConfig:
    """Tunables of :class:`~prml2_edge.runtime.plausibility.Plausibility` (SI units). Chosen on the simulated
    fleet's training cars (``benchmarks/reliability.py`` reports the held-out car);
    docs/reliability.md explains each."""

    enabled: bool = True
    min_speed_mps: float = 5.0  # cross-checks run above this speed
    smooth_s: float = 0.25  # EMA time constant of the speed and brake residuals
    smooth_rot_s: float = 0.4  # and of the rotation residuals (yaw rate, a_y, steering: transients lead and lag)
    confirm_s: float = 0.15  # smoothed residual above tolerance this long: flagged
    clear_s: float = 1.0  # below half the tolerance this long: cleared
    warmup_s: float = 10.0  # driving time before a learned relation takes part in the checks
    learn_tau_s: float = 120.0  # forgetting time of the learned relations
    half_track_m: float = 0.78  # lever arm of the wheels (the effective track is learned per axle)
    steering_ratio: float = 15.0  # only for the front wheels' steer correction
    wheel_tol_mps: float = 0.3
    wheel_tol_rel: float = 0.04
    wheel_vote_tol_mps: float = 0.15  # a wheel further than this from the others does not vote on the rotation
    wheel_slip_per_mps2: float = 0.015  # driven and braked wheels slip: relative tolerance per m/s^2 of |a_x|
    speedo_tol_mps: float = 0.6
    speedo_tol_rel: float = 0.05
    speedo_lag_s: float = 0.25  # the instrument's low-pass
    yaw_tol_radps: float = 0.4 * _DEG
    yaw_tol_rel: float = 0.04
    ay_tol_mps2: float = 0.45
    ay_tol_rel: float = 0.15
    steer_tol_rad: float = 6.0 * _DEG
    steer_tol_rel: float = 0.25
    res_gain: float = 0.5  # tolerance per resolution step of the signal (quantisation)
    # sensors lag each other (yaw-rate and a_y filters, the car's yaw response behind the steering): tolerance
    # per unit of the yaw acceleration, as a time [s]
    lag_yaw_s: float = 0.02  # the yaw-rate sensor and the wheels
    lead_ay_s: float = 0.08  # a_y leads the yaw rate by the side-slip rate
    lead_steer_s: float = 0.15  # the steering leads it by the car's yaw response
    # the wheel- and steering-based rotation estimates pass a first-order lag like the inertial sensors' filters
    inertial_lag_s: float = 0.04
    brake_tol_mps2: float = 0.9  # pressure higher than the deceleration supports (stuck high)
    brake_tol_low_mps2: float = 1.8  # deceleration the pressure does not explain (coasting, engine braking)
    brake_tol_rel: float = 0.3
    brake_min_bar: float = 3.0  # pressure above idle that counts as braking (learning the gain)
    wheel_yaw_max_accel_mps2: float = 2.5  # the wheel pairs estimate the rotation below this |a_x| ...
    wheel_yaw_slip: float = 0.001  # ... with an uncertainty of this times |a_x a_y| v / track (left/right slip)
    learned_sd: bool = True  # ... plus the uncertainty of the pair's learned track and radius difference
    ay_check_max_mps2: float = 6.0  # rotation relations are linear below this lateral acceleration
    stuck_hold_s: float = 0.5
    dropout_tol: float = 4.0  # a signal reading 0 this many tolerances from its prediction is flagged at once
    stuck_res_steps: float = 5.0  # ... while the smoothed prediction moved by this many resolution steps ...
    stuck_span_tol: float = 0.5  # ... plus this many absolute tolerances
    substitute_stale: bool = True  # a stale signal (message stopped) gets the others' prediction too
    substitute_yaw_std_radps: float = 0.5 * _DEG  # uncertainty of the others' yaw rate (the filter's cue from it)
    # offset jumps of the yaw rate, a_y and steering: a step in the signal's own first difference (beyond
    # jump_noise_gain times its usual innovation) that the residual follows (its mean over jump_after_s, from
    # jump_lag_s after the step, moved by the step within jump_match of it, against jump_before_s before)
    jump_noise_gain: float = 6.0
    jump_lag_s: float = 0.1  # yaw rate (the motion cannot step: the others follow a real change within 0.1 s) ...
    jump_lag_ay_s: float = 0.3  # ... a_y and the steering: the car's response to a steering step settles first
    jump_lag_steer_s: float = 0.5
    jump_after_s: float = 0.3
    jump_before_s: float = 0.5
    jump_match: float = 0.3
    jump_others_still: float = 0.5  # steering: the others' prediction moved by less than this part of the step
    jump_sharp: float = 0.25  # the differences next to the step stay within this part of it
    jump_steady: float = 0.15  # the residual before and after the step varies by at most this part of it
    jump_drop_s: float = 0.5  # the value less the offset worse than the value itself this long: the correction ends
    jump_min_yaw_radps: float = 1.0 * _DEG  # smallest offset jump looked for (a real step of the motion is smaller)
    jump_min_ay_mps2: float = 0.7
    jump_min_steer_rad: float = 7.0 * _DEG
    jump_steer_max_ay_mps2: float = 5.0
    max_substituted: int = 3  # at most this many signals replaced at once (a whole ESP message is two)
