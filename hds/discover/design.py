"""Excitation designed through the differentiable simulator (optimal experiment design).

Discovery's fit (`hds.discover.fit`) identifies candidate effects from k-step windows: each
window starts at a measured state, replays the measured controls for k steps and is compared
with the measured observations. How well an excitation identifies a parameter is the curvature
of that fit, J^T J, J the windows' sensitivities to the parameter; hds has J exactly, forward
mode through the simulator whose candidates' parameters are traced inputs (`Model.params`).
So the excitation can be optimised before the plant is touched:

  controls   u(t) = clip(u_ff(t) - K (x(t) - x_ref), mid +- amplitude x half range)
             u_ff(t) = mid + amplitude x half range x w(t), w(t) in [-1, 1] either
             per step (default, `parameterisation="per_step"`): every step's w a free
             variable, projected back into [-1, 1] after each Adam update; or
             `"fourier"`: w(t) = tanh(sum_h a_h sin(2 pi f_h t) + b_h cos(2 pi f_h t)),
             f_h = h f_max / H, h = 1..H (smooth, a subset of the per-step signals); K a
             stabilising feedback (LQR, `lqr_gain`, or a policy's linearisation) for a system
             that cannot be excited open loop, zero by default
  information  I = sum over windows of J_w^T Sigma^-1 J_w, J_w = d(window's prediction)/d theta
             on the trajectory the current estimate predicts, Sigma the measurement noise
             (measured on the data so far from the model's one-step residuals at the
             estimate, `Designer.sensor_noise`), parameters in units of their size
  criterion  D: -log det I (default); A: trace I^-1; "<effect>@<target>.<param>": that
             parameter's variance (I^-1)_jj
  limits     the actuators' range (scaled by the amplitude bound), the joints' range (minus a
             margin) and a speed bound per joint, as penalties during the optimisation (Adam on
             w or the coefficients; the best iterate that keeps them on the model) and as a
             check on the predicted trajectory after it: the feedforward amplitude is shrunk
             until the trajectory keeps every limit.

`Design.predicted_half` are the typical 95% half-widths the recorded windows will give
discovery's fit (measured initial states): the fit's estimator is linear in the noise near
the optimum, theta_hat - theta = H^-1 J_s^T r_s(n), so its covariance H^-1 B B^T H^-1 (B =
d(J_s^T r_s)/dn, through the simulator too) holds the windows' overlap exactly; E episodes
divide it by E, and the half-width takes the t quantile over episodes, as
`confidence_intervals` does, and the median of a cluster-robust standard error over E
episodes (`typical_scale`). A law mismatch (a plant whose laws are not the library's) enters
as a disturbance of each step whose state-dependent variance is measured on the records so far
(`Designer.mismatch`, `Mismatch`, `calibrated` to the fit's noise part): its pull joins B, so
the criterion and the prediction hold it (`mismatch=`; None: sensor noise alone).

    from hds.discover.design import Designer
    designer = Designer(env_cfg, ["coulomb_friction@slider"], dt=0.04, steps=100)
    design = designer.design({"coulomb_friction@slider": {"force": 60.0}}, x0, noise)
    u = design.controls()            # [T, n_act], or design.controller() for the feedback
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np
import optax
import scipy.linalg
import scipy.optimize
from scipy import stats

from hds.discover.fit import config_key, get_engine
from hds.envs.system import load_spec

log = logging.getLogger("hds")

CRITERIA = ("D", "A")
PARAMETERISATIONS = ("per_step", "fourier")
# Adam's iterations and step per parameterisation. On the cart-pole at the true values
# (experiments/excitation_design), best standard signal's plant time over the design's: 60
# Fourier iterations 1.6-2.4x, 400 2.1-3.7x; per step from one start, 300 iterations at a
# step of 0.05: 2.5-2.7x, at 0.2: 2.9-3.2x (1000: 3.3-4.3x; two effects 1.7-2.5x, 1000: 3.3x)
ITERATIONS = {"per_step": 300, "fourier": 60}
LEARNING_RATE = {"per_step": 0.2, "fourier": 0.1}
PENALTY = 1e3  # weight of a limit's squared violation (in units of the limit) against the criterion
RIDGE = 1e-9  # relative ridge on the information: a parameter no window sees stays finite
EIVAL_FLOOR = 1e-12
FLOOR_Z = 1.96  # standard errors of a measured noise floor a misfit must exceed (WindowFit)


@dataclass(frozen=True)
class Limits:
    """What the designed record must keep: control bounds [n_act] (the amplitude bound already
    applied), joint position bounds [nq] (+-inf: none) and speed bounds [nv] (inf: none)."""

    u_low: np.ndarray
    u_high: np.ndarray
    q_low: np.ndarray
    q_high: np.ndarray
    max_speed: np.ndarray

    def violation(self, obs: np.ndarray, u: np.ndarray) -> dict[str, float]:
        """The largest excess over each limit on a trajectory (obs [T+1, n_obs], u [T, n_act]);
        0 where kept."""
        nq = len(self.q_low)
        q, qd = obs[..., :nq], obs[..., nq:]
        return {
            "control": float(max(np.max(u - self.u_high), np.max(self.u_low - u), 0.0)),
            "joint": float(max(np.max(q - self.q_high), np.max(self.q_low - q), 0.0)),
            "speed": float(max(np.max(np.abs(qd) - self.max_speed), 0.0)),
        }


def limits_of(
    env_cfg, amplitude: float = 1.0, max_speed=None, joint_margin: float = 0.05
) -> Limits:
    """The limits of an env's system: its actuators' ctrlrange shrunk to `amplitude` of the
    half range about the middle, its limited joints' range less `joint_margin` of it at each
    end (the rail's ends), and `max_speed` per joint (a number or a list over the joints;
    None: none)."""
    if not 0 < amplitude <= 1:
        raise ValueError(f"amplitude = {amplitude} must lie in (0, 1] (share of the half range)")
    if not 0 <= joint_margin < 0.5:
        raise ValueError(f"joint_margin = {joint_margin} must lie in [0, 0.5) (share of a range)")
    model = load_spec(env_cfg.xml, env_cfg.timestep).compile()
    ctrl = np.array(model.actuator_ctrlrange, dtype=np.float64)
    if not model.actuator_ctrllimited.all():
        bad = [model.actuator(a).name for a in range(model.nu) if not model.actuator_ctrllimited[a]]
        raise ValueError(
            f"actuator(s) {bad} have no control range: an excitation is designed within "
            "finite limits; give them a ctrlrange in the MJCF"
        )
    mid, half = ctrl.mean(1), 0.5 * (ctrl[:, 1] - ctrl[:, 0]) * amplitude
    nq = model.nq
    q_low, q_high = np.full(nq, -np.inf), np.full(nq, np.inf)
    for j in range(model.njnt):
        if model.jnt_limited[j]:
            lo, hi = model.jnt_range[j]
            pad = joint_margin * (hi - lo)
            q_low[model.jnt_qposadr[j]], q_high[model.jnt_qposadr[j]] = lo + pad, hi - pad
    speed = np.full(model.nv, np.inf)
    if max_speed is not None:
        speed = np.broadcast_to(np.asarray(max_speed, dtype=np.float64), (model.nv,)).copy()
        if (speed <= 0).any():
            raise ValueError(f"max_speed = {max_speed} must be positive (per joint)")
    return Limits(mid - half, mid + half, q_low, q_high, speed)


@dataclass(frozen=True)
class Mismatch:
    """A law mismatch modelled as a disturbance of each step, x_(t+1) = f(x_t, u_t) + d_t, white
    between steps, of variance var_o(x, u) = features(x, u) . coef_o per observed signal o
    (`Designer.mismatch` estimates it from the fit's one-step residuals). The features say
    where laws differ: everywhere (1), near a joint's rest (exp(-(v / rest_speed)^2) and the
    same four times wider: a smoothed friction against a plant's stiction or soft constraint),
    with the speed ((v / speed_scale)^2: a damping law) and with the drive (((u - mid) / half)^2:
    a gain or a motor law). `scale` multiplies every variance (`calibrated`: as the fit's noise
    part sees it)."""

    coef: np.ndarray  # [n_obs, F] the variance per unit feature, per observed signal
    rest_speed: np.ndarray  # [nv] a joint's speed within which it counts as at rest
    speed_scale: np.ndarray  # [nv]
    u_mid: np.ndarray  # [n_act]
    u_half: np.ndarray  # [n_act]
    scale: float = 1.0

    def arrays(self) -> tuple:
        """The traced form (`_mismatch_std`): the coefficients with `scale` applied."""
        return _f32(
            self.coef * self.scale, self.rest_speed, self.speed_scale, self.u_mid, self.u_half
        )

    def variance(self, obs, u) -> np.ndarray:
        """[..., n_obs] the disturbance's variance at the states obs [..., n_obs] and controls
        u [..., n_act] (obs the state a step starts from)."""
        nq = obs.shape[-1] - len(self.rest_speed)
        f = _mismatch_features(
            np.asarray(obs, np.float64),
            np.asarray(u, np.float64),
            nq,
            self.rest_speed,
            self.speed_scale,
            self.u_mid,
            self.u_half,
        )
        return np.asarray(f, np.float64) @ (self.coef * self.scale).T

    def scaled(self, factor: float) -> Mismatch:
        return dataclasses.replace(self, scale=self.scale * float(factor))


def _mismatch_features(obs, u, nq, rest_speed, speed_scale, u_mid, u_half):
    """[..., F] the mismatch model's features (`Mismatch`) at states obs and controls u;
    numpy or traced."""
    xp = jnp if isinstance(obs, jax.Array) else np
    v = obs[..., nq:]
    z = v / rest_speed
    return xp.concatenate(
        [
            xp.ones(v.shape[:-1] + (1,), v.dtype),
            xp.exp(-(z**2)),
            xp.exp(-((z / 4.0) ** 2)),
            (v / speed_scale) ** 2,
            ((u - u_mid) / u_half) ** 2,
        ],
        axis=-1,
    )


@dataclass(frozen=True)
class MismatchMean:
    """A law mismatch's mean as a function of the state and the drive: the plant steps
    x_(t+1) = f(x_t, u_t) + m(x_t, u_t) (+ noise), m_o(x, u) = features(x, u) . coef_o per
    observed signal o (`Designer.mismatch_mean` regresses the fit's one-step residuals on
    them). A law that differs from the library's is deterministic in the state: for one
    signal it shifts the estimate, H^-1 J^T (the windows' response to m), rather than adding
    scatter (`Mismatch`, a white disturbance, models what averages away; this what does not).
    The features, signed: a constant; each joint's position (an angle's sine and cosine, a
    slider's position and its square over its spread); its speed over its spread and the
    speed times its size (damping and drag laws); tanh of the speed over `rest_speed` and four
    times wider, and a bump exp(-(v / rest_speed)^2) (a friction's reversal, stiction, a soft
    constraint); and the drive ((u - mid) / half: a gain or a motor law)."""

    coef: np.ndarray  # [n_obs, F] the mean per unit feature, per observed signal
    rest_speed: np.ndarray  # [nv]
    speed_scale: np.ndarray  # [nv]
    q_scale: np.ndarray  # [nq] a slider's position spread (an angle's: unused)
    angular: np.ndarray  # [nq] which joints are hinges (sine and cosine features)
    u_mid: np.ndarray  # [n_act]
    u_half: np.ndarray  # [n_act]

    def arrays(self) -> tuple:
        """The traced form (`Designer._mean_arrays`)."""
        return _f32(
            self.coef,
            self.rest_speed,
            self.speed_scale,
            self.q_scale,
            np.asarray(self.angular, np.float64),
            self.u_mid,
            self.u_half,
        )

    def features(self, obs, u) -> np.ndarray:
        """[..., F] the features at the states obs [..., n_obs] and controls u [..., n_act]."""
        scales = (self.rest_speed, self.speed_scale, self.q_scale, self.angular)
        return _mean_features(
            np.asarray(obs, np.float64),
            np.asarray(u, np.float64),
            *(np.asarray(x, np.float64) for x in (*scales, self.u_mid, self.u_half)),
        )

    def mean(self, obs, u) -> np.ndarray:
        """[..., n_obs] the mismatch's mean at the states obs [..., n_obs] (the step's start)
        and controls u [..., n_act]."""
        return self.features(obs, u) @ np.asarray(self.coef, np.float64).T


def _mean_features(obs, u, rest_speed, speed_scale, q_scale, angular, u_mid, u_half):
    """[..., F] the features of `MismatchMean` at states obs and controls u; numpy or traced
    (angular a float mask: 1 for a hinge)."""
    xp = jnp if isinstance(obs, jax.Array) or isinstance(rest_speed, jax.Array) else np
    nq = q_scale.shape[-1]
    q, v = obs[..., :nq], obs[..., nq:]
    qs = q / q_scale
    pos_a = angular * xp.sin(q) + (1.0 - angular) * qs
    pos_b = angular * xp.cos(q) + (1.0 - angular) * qs**2
    z = v / rest_speed
    vs = v / speed_scale
    return xp.concatenate(
        [
            xp.ones(v.shape[:-1] + (1,), v.dtype),
            pos_a,
            pos_b,
            vs,
            vs * xp.abs(vs),
            xp.tanh(z),
            xp.tanh(z / 4.0),
            xp.exp(-(z**2)),
            (u - u_mid) / u_half,
        ],
        axis=-1,
    )


@dataclass
class Design:
    """A designed excitation and what it is predicted to give."""

    coefficients: np.ndarray | None  # [n_act, 2H] Fourier coefficients (sine, then cosine)
    amplitude: np.ndarray  # [n_act] the feedforward's half swing (after any shrinking)
    middle: np.ndarray  # [n_act]
    frequencies: np.ndarray  # [H] Hz
    dt: float
    steps: int
    gain: np.ndarray  # [n_act, n_obs] feedback K (zeros: open loop)
    x_ref: np.ndarray  # [n_obs]
    angular: np.ndarray  # [n_obs] which deviations wrap (hinge angles)
    limits: Limits
    keys: list[str]  # fitted parameters, "<effect>@<target>.<param>"
    predicted_se: np.ndarray  # [M] per episode (divide by sqrt(E) for E episodes)
    trajectory: np.ndarray  # [T+1, n_obs] predicted at the estimate
    planned_controls: np.ndarray  # [T, n_act] the controls along it
    criterion: str = "D"  # as given (a dict of asked widths as its str)
    history: list[float] = field(default_factory=list)  # the criterion per iteration
    # "designed", or the name of the rival signal the model predicted better (`design`'s
    # rivals): then planned_controls are that signal's, applied open loop
    signal: str = "designed"
    # [T, n_act] the per-step feedforward w in [-1, 1] (parameterisation "per_step"; None: the
    # Fourier series of `coefficients`)
    waveform: np.ndarray | None = None
    # [M] the shift the law mismatch's mean drags an estimate by (`Designer.predicted_shift`;
    # None: designed without a `MismatchMean`)
    predicted_shift: np.ndarray | None = None

    @property
    def parameterisation(self) -> str:
        return "fourier" if self.waveform is None else "per_step"

    def unit_feedforward(self) -> np.ndarray:
        """[T, n_act] w(t) in [-1, 1]: the feedforward before its swing and middle."""
        if self.waveform is not None:
            return np.asarray(self.waveform, np.float64)
        wave = _feedforward(self.coefficients, self.frequencies, self.dt, self.steps)
        return np.asarray(wave, np.float64)

    def feedforward(self) -> np.ndarray:
        """[T, n_act] the feedforward u_ff."""
        return self.unit_feedforward() * self.amplitude + self.middle

    def controls(self) -> np.ndarray:
        """[T, n_act] the controls to apply open loop: the planned ones (with feedback, those
        it gave on the predicted trajectory; use `controller` to close the loop on a plant)."""
        return np.array(self.planned_controls)

    def controller(self):
        """A policy obs [B, n_obs] -> u [B, n_act] for `hds.data.collect`, stepping through the
        design: u = clip(u_ff(t) - K (obs - x_ref)); t counts calls and restarts after T."""
        ff, t = self.feedforward(), [0]
        if self.signal != "designed":  # a rival signal won: its controls, open loop
            ff = self.planned_controls

        def act(obs):
            dx = np.asarray(obs, dtype=np.float64) - self.x_ref
            dx = np.where(self.angular, np.arctan2(np.sin(dx), np.cos(dx)), dx)
            u = ff[t[0] % self.steps] - dx @ self.gain.T
            t[0] += 1
            return np.clip(u, self.limits.u_low, self.limits.u_high)

        return act

    def predicted_half(self, episodes: int, level: float = 0.95) -> np.ndarray:
        """[M] the median half-widths of the `level` intervals the fit reports from `episodes`
        episodes of this design (`half_width`)."""
        return half_width(self.predicted_se, episodes, level)


def typical_scale(episodes: int) -> float:
    """The median of the fit's standard error over the true one, from `episodes` episodes.
    The fit's noise part is a sandwich with episodes as clusters (`confidence_intervals`): its
    meat is the scatter of the episodes' gradients, which sum to zero at the fit, so each
    variance is the true one times chi2_(E-1) / (E-1), and the standard error's median is
    sqrt(median chi2_(E-1) / (E-1)) of the true: 0.67 at 2 episodes, 0.89 at 4, 0.95 at 8,
    0.98 at 16. (Its mean, not its median, is the true variance: a width predicted without
    this is the width of a typical record only for many episodes.)"""
    if episodes < 2:
        raise ValueError(f"episodes = {episodes}: a cluster-robust error needs at least 2")
    k = episodes - 1
    return math.sqrt(stats.chi2.median(k) / k)


def half_width(se, episodes: int, level: float = 0.95) -> np.ndarray:
    """[M] the median half-widths of the `level` intervals the fit reports from `episodes`
    episodes whose per-episode standard errors are `se` [M]: the Student-t quantile over the
    episodes x se / sqrt(E) x `typical_scale(E)`; inf below 2 episodes."""
    se = np.asarray(se, np.float64)
    if episodes < 2:
        return np.full(se.shape, np.inf)
    t = stats.t.ppf(0.5 + level / 2, episodes - 1)
    return t * se / math.sqrt(episodes) * typical_scale(episodes)


def _feedforward(coefficients, frequencies, dt, steps):
    """tanh of the Fourier series, [T, n_act] in [-1, 1]."""
    t = jnp.arange(steps) * dt
    phase = 2 * jnp.pi * t[:, None] * jnp.asarray(frequencies)[None, :]  # [T, H]
    basis = jnp.concatenate([jnp.sin(phase), jnp.cos(phase)], axis=1)  # [T, 2H]
    return jnp.tanh(basis @ jnp.asarray(coefficients).T)


_DESIGNERS: dict[tuple, Designer] = {}


def get_designer(env_cfg, keys, dt, steps, horizon=10, stride=1, harmonics=8, max_frequency=None):
    """The Designer for this simulator, parameters and record length, built once per process
    and then reused (as `get_engine` reuses the fit's engine): its programs take the estimate,
    noise, limits and initial states as traced inputs, so a sequential design's rounds and the
    loop's records trace nothing twice."""
    key = (
        config_key(env_cfg),
        tuple(keys),
        round(float(dt), 12),
        int(steps),
        int(horizon),
        int(stride),
        int(harmonics),
        max_frequency,
    )
    if key not in _DESIGNERS:
        _DESIGNERS[key] = Designer(
            env_cfg, list(keys), dt, steps, horizon, stride, harmonics, max_frequency
        )
    return _DESIGNERS[key]


class Designer:
    """The compiled pieces for one simulator, one set of fitted parameters and one record
    length: built once, reused for every design (every round of a sequential design).

    `keys` are candidate effects "<effect>@<target>" (every parameter of each is fitted) of
    `env_cfg`'s simulator; `steps` the episode length in environment steps of `dt` seconds;
    `horizon`/`stride` the fit's windows (discover.horizon, discover.stride)."""

    def __init__(
        self,
        env_cfg,
        keys: list[str],
        dt: float,
        steps: int,
        horizon: int = 10,
        stride: int = 1,
        harmonics: int = 8,
        max_frequency: float | None = None,
    ):
        if not keys:
            raise ValueError(
                "give the candidate effects to design for, e.g. ['coulomb_friction@slider']"
            )
        if steps < horizon + 1:
            raise ValueError(
                f"steps = {steps} is too short for windows of horizon = {horizon} steps: "
                "design a longer episode or lower the horizon"
            )
        names = sorted({k.split("@", 1)[0] for k in keys})
        engine = get_engine(env_cfg, dt, names, 0, 0, horizon)
        self.engine, self.model = engine, engine.model
        self.sim = self.model.sim
        by_key = {c.key: c for c in self.model.candidates}
        unknown = [k for k in keys if k not in by_key]
        if unknown:
            raise ValueError(
                f"no candidate {unknown} on this simulator; candidates of {names}: {sorted(by_key)}"
            )
        self.keys = list(keys)
        self.candidates = [by_key[k] for k in keys]
        self.slots = np.array([s for c in self.candidates for s in c.slots], np.int32)
        self.labels = [f"{c.key}.{p}" for c in self.candidates for p in c.params]
        self.dt, self.steps, self.horizon, self.stride = float(dt), int(steps), horizon, stride
        nyquist = 0.5 / dt
        f_max = min(max_frequency or 0.25 * nyquist, nyquist)
        if harmonics < 1 or not f_max > 0:
            raise ValueError(f"harmonics = {harmonics} >= 1 and max_frequency > 0 are needed")
        self.frequencies = f_max * np.arange(1, harmonics + 1) / harmonics
        self.starts = np.arange(0, steps - horizon + 1, stride, dtype=np.int32)
        angular = np.zeros(self.sim.n_obs, bool)
        angular[: self.sim.nq] = self.sim.angular
        self.angular = angular
        self._rollout = jax.jit(self._rollout_fn)
        self._jac = jax.jit(self._jacobian)
        self._predict = jax.jit(lambda *a: self._parts(*a)[:3])
        self._predict_open = jax.jit(self._parts_open)
        self._rollout_open = jax.jit(self._open_rollout)
        self._one_step = jax.jit(self._one_step_fn)
        self._record = jax.jit(self._record_fn)
        self._noise_loss = jax.jit(self._noise_loss_fn)
        self._steps = {}  # the optimiser's step per learning rate, compiled on first use

    # -- parameters -----------------------------------------------------------------------

    def theta(self, estimate: dict | None = None) -> np.ndarray:
        """theta with every candidate off, but the given estimates {key: {param: value}}."""
        theta = np.array(self.model.nominal, np.float64)
        for cand in self.candidates:
            for p, s in zip(cand.params, cand.slots, strict=True):
                if estimate and cand.key in estimate and p in estimate[cand.key]:
                    theta[s] = float(estimate[cand.key][p])
        return theta

    def reference(self, theta: np.ndarray) -> np.ndarray:
        """[M] each fitted parameter's size (its estimate, else its nominal, else 1): the
        information is scaled by it, so A-optimality weighs relative variances."""
        value = np.abs(theta[self.slots])
        nominal = np.abs(np.asarray(self.model.nominal, np.float64)[self.slots])
        return np.where(value > 0, value, np.where(nominal > 0, nominal, 1.0))

    # -- the simulator pieces (traced) --------------------------------------------------------

    def _rollout_fn(self, theta, ff, gain, x_ref, x0, low, high):
        """The trajectory the model predicts, [T+1, n_obs], and its controls [T, n_act], of
        the feedforward ff [T, n_act] with the feedback gain about x_ref, clipped to low..high."""
        sim, params = self.sim, self.model.params(theta)
        state = sim.init(x0[: sim.nq], x0[sim.nq :], params)

        def step(state, u_ff):
            obs = sim.observe(params, state)
            dx = obs - x_ref
            dx = jnp.where(self.angular, jnp.arctan2(jnp.sin(dx), jnp.cos(dx)), dx)
            u = jnp.clip(u_ff - gain @ dx, low, high)
            return sim.step(params, state, u), (obs, u)

        last, (obs, u) = jax.lax.scan(step, state, ff)
        obs = jnp.concatenate([obs, sim.observe(params, last)[None]])
        return jnp.nan_to_num(obs, nan=1e3, posinf=1e3, neginf=-1e3), u

    def residuals(self, theta, obs, u, weight):
        """Every window's k-step prediction minus obs, times weight [n_obs], flat."""
        model, k = self.model, self.horizon
        params = model.params(theta)
        empty = jnp.zeros((0, u.shape[-1]), u.dtype)

        def one(s):
            pred = model.window(params, obs[s], empty, jax.lax.dynamic_slice_in_dim(u, s, k))
            err = pred - jax.lax.dynamic_slice_in_dim(obs, s + 1, k)
            return jnp.where(self.angular, jnp.arctan2(jnp.sin(err), jnp.cos(err)), err)

        return (jax.vmap(one)(jnp.asarray(self.starts)) * weight).reshape(-1)

    def _jacobian(self, theta, obs, u, weight):
        """[R, M] the windows' sensitivities to the fitted parameters (forward mode), the
        trajectory held as measured (what the fit linearises)."""
        slots = jnp.asarray(self.slots)

        def res(values):
            return self.residuals(theta.at[slots].set(values), obs, u, weight)

        return jax.jacfwd(res)(theta[slots])

    def _one_step_fn(self, theta, obs, u):
        """Every step's one-step prediction from its measured state minus the next measurement,
        [T, n_obs], and the prediction's sensitivity to that state A_t [T, n_obs, n_obs]."""
        model, params = self.model, self.model.params(theta)
        empty = jnp.zeros((0, u.shape[-1]), u.dtype)

        def one(x, ut, target):
            def pred(x):
                return model.window(params, x, empty, ut[None])[0]

            err = pred(x) - target
            err = jnp.where(self.angular, jnp.arctan2(jnp.sin(err), jnp.cos(err)), err)
            return err, jax.jacfwd(pred)(x)

        return jax.vmap(one)(obs[:-1], u, obs[1:])

    def sensor_noise(self, theta, obs, u) -> np.ndarray:
        """[n_obs] the measurement noise std of records obs [E, T+1, n_obs] of controls
        u [E, T, n_act], from the model's one-step residuals at theta (the fit's estimate).

        Differences of the measurements (`hds.discover.data.noise_level`) hold the motion
        itself wherever the sampled motion is not smooth at the sample rate: a cart's velocity
        under a PRBS or a 3 Hz chirp at 25 Hz has fourth differences of several times its
        sensor noise with no noise at all. The model removes the motion: from a measured state
        y_t = x_t + n_t the one-step residual is r_t = A_t n_t - n_(t+1) (A_t the prediction's
        sensitivity to its initial state), so white noise of variances s gives
        E[r_t,o^2] = sum_p A_t,op^2 s_p + s_o: a linear system in s over the records. Each
        residual's variance is taken robustly (its median absolute deviation), so a law
        mismatch confined to a few steps (a friction's reversals) does not count as noise;
        one spread over every step does (then this is the residual level the fit sees). The
        fitted parameters take a handful of degrees of freedom from E x T residuals: ignored."""
        return self._sensor_noise(theta, *_records(obs, u))[0]

    def _one_step_residuals(self, theta, obs, u) -> tuple[np.ndarray, np.ndarray]:
        """Every step's one-step residual [N, n_obs] over the records and its squared
        sensitivity to the initial state [N, n_obs, n_obs] (`_one_step`), record by record."""
        theta32 = jnp.asarray(theta, jnp.float32)
        res, sens = [], []
        for o, a in zip(obs, u, strict=True):
            r, jac = self._one_step(theta32, *_f32(o, a))
            res.append(np.asarray(r, np.float64))
            sens.append(np.asarray(jac, np.float64) ** 2)
        return np.concatenate(res), np.concatenate(sens)

    def _sensor_noise(self, theta, obs, u) -> tuple[np.ndarray, int]:
        """`sensor_noise` and how many steps' residuals it was taken from."""
        res, sens = self._one_step_residuals(theta, obs, u)
        eye = np.eye(obs.shape[-1])

        def solve(keep):
            r = res[keep]
            var = (np.median(np.abs(r - np.median(r, axis=0)), axis=0) / 0.6745) ** 2
            return np.sqrt(scipy.optimize.nnls(sens[keep].mean(axis=0) + eye, var)[0])

        sigma = solve(np.ones(len(res), bool))
        # a joint within the noise of rest: the smoothed laws (a friction's tanh of width
        # 1 / sharpness) are not linear over the noise there, and a plant's stiction is not
        # what they model; those steps' residuals are left out (if a fifth of them remain:
        # a few hundred residuals hold a median to a few percent)
        nq = self.sim.nq
        speed = np.abs(obs[:, :-1, nq:]).reshape(-1, obs.shape[-1] - nq)
        slow = (speed < 1.0 / self.sim.sharpness + 3.0 * sigma[nq:]).any(axis=1)
        if np.mean(slow) < 0.8:
            return solve(~slow), int(np.sum(~slow))
        return sigma, len(res)

    def mismatch(self, theta, obs, u, noise) -> Mismatch:
        """The law mismatch on records obs [E, T+1, n_obs] of controls u [E, T, n_act] at theta
        (the fit's estimate) beside the sensor noise of std `noise` [n_obs] (`sensor_noise`):
        what the model's one-step residuals hold beyond the noise, as a disturbance of each
        step whose variance depends on the state and the drive (`Mismatch`).

        From a measured state the one-step residual is r_t = A_t n_t - n_(t+1) - d_t, so
        E[r_t,o^2] = sum_p A_t,op^2 s_p + s_o + var_o(x_t, u_t): the excess of each squared
        residual over the noise's share is regressed on the features (non-negative least
        squares per signal, the mean of the squares: what the fit's quadratic loss sees,
        the large residuals of a friction's reversals included). A disturbance spread alike
        over every step of a signal is, by its variance, indistinguishable from that signal's
        sensor noise (`sensor_noise`'s robust scale counts it there); one confined to some
        states (a joint near rest, a fast or a hard-driven one) is what this separates."""
        obs, u = _records(obs, u)
        noise = np.maximum(np.asarray(noise, np.float64), 0.0)
        res, sens = self._one_step_residuals(theta, obs, u)
        excess = res**2 - (sens @ noise**2 + noise**2)  # [N, n_obs]
        nq = self.sim.nq
        states = obs[:, :-1].reshape(-1, obs.shape[-1])
        speed = states[:, nq:]
        rest = 1.0 / self.sim.sharpness + 3.0 * noise[nq:]
        speed_scale = np.maximum(speed.std(axis=0), rest)
        ctrl = np.asarray(self.sim.ctrl_range, np.float64)
        mid, half = ctrl.mean(1), np.maximum(0.5 * (ctrl[:, 1] - ctrl[:, 0]), 1e-12)
        feats = _mismatch_features(
            states, u.reshape(-1, u.shape[-1]), nq, rest, speed_scale, mid, half
        )
        # each feature in units of its mean, so the least squares is conditioned alike
        size = np.maximum(feats.mean(axis=0), 1e-12)
        coef = np.stack([scipy.optimize.nnls(feats / size, e)[0] / size for e in excess.T])
        return Mismatch(coef, rest, speed_scale, mid, half)

    def mismatch_mean(self, theta, obs, u, noise, ridge: float = 1e-3) -> MismatchMean:
        """The law mismatch's mean on records obs [E, T+1, n_obs] of controls u [E, T, n_act]
        at theta (the fit's estimate), the sensor noise of std `noise` [n_obs] beside it: the
        one-step residuals' signed regression on the state and the drive (`MismatchMean`).

        From a measured state the one-step residual is r_t = A_t n_t - n_(t+1) - m(x_t, u_t):
        the noise has mean zero, so least squares of -r_t on the features at the measured
        state estimates m (per observed signal; each feature in units of its root mean
        square, a `ridge` relative to the features' Gram matrix's mean diagonal: features
        the record does not tell apart, e.g. an angle's cosine and the constant while it
        hangs, share their part rather than cancel in large opposite coefficients). At the
        fit's estimate the part of the mismatch the candidates' own laws can take has been
        taken: what stays is what drags another signal's estimate away from this one."""
        obs, u = _records(obs, u)
        noise = np.maximum(np.asarray(noise, np.float64), 0.0)
        res, _ = self._one_step_residuals(theta, obs, u)
        nq = self.sim.nq
        states = obs[:, :-1].reshape(-1, obs.shape[-1])
        rest = 1.0 / self.sim.sharpness + 3.0 * noise[nq:]
        speed_scale = np.maximum(states[:, nq:].std(axis=0), rest)
        q_scale = np.maximum(states[:, :nq].std(axis=0), 1e-6)
        ctrl = np.asarray(self.sim.ctrl_range, np.float64)
        mid, half = ctrl.mean(1), np.maximum(0.5 * (ctrl[:, 1] - ctrl[:, 0]), 1e-12)
        angular = np.asarray(self.angular[:nq], bool)
        made = MismatchMean(
            np.zeros((obs.shape[-1], 0)), rest, speed_scale, q_scale, angular, mid, half
        )
        feats = made.features(states, u.reshape(-1, u.shape[-1]))
        size = np.maximum(np.sqrt(np.mean(feats**2, axis=0)), 1e-12)
        x = feats / size
        gram = x.T @ x
        gram += ridge * np.trace(gram) / len(gram) * np.eye(len(gram))
        coef = np.linalg.solve(gram, x.T @ (-res)).T / size  # [n_obs, F]
        return dataclasses.replace(made, coef=coef)

    def _mean_arrays(self, mean: MismatchMean | None) -> tuple:
        """The traced mismatch-mean arguments: `mean`'s, or none (zero), so a design with and
        one without share one program."""
        nq, n_obs, n_act = self.sim.nq, self.sim.n_obs, self.sim.n_act
        nv = n_obs - nq
        if mean is None:
            n_feat = 1 + 2 * nq + 5 * nv + n_act
            angular = np.asarray(self.angular[:nq], np.float64)
            return _f32(
                np.zeros((n_obs, n_feat)), *np.ones((2, nv)), np.ones(nq), angular,
                *np.ones((2, n_act)),
            )  # fmt: skip
        if mean.coef.shape[0] != n_obs:
            raise ValueError(
                f"mismatch_mean has {mean.coef.shape[0]} signals; this simulator observes "
                f"{n_obs}: estimate it with this designer (`Designer.mismatch_mean`)"
            )
        return mean.arrays()

    def _mis(self, mismatch: Mismatch | None) -> tuple:
        """The traced mismatch arguments: `mismatch`'s, or none (zero variance), so a design
        with and one without share one program."""
        if mismatch is None:
            nv, n_act = self.sim.n_obs - self.sim.nq, self.sim.n_act
            n_feat = 1 + 3 * nv + n_act
            return _f32(np.zeros((self.sim.n_obs, n_feat)), *np.ones((2, nv)), *np.ones((2, n_act)))
        if mismatch.coef.shape[0] != self.sim.n_obs:
            raise ValueError(
                f"mismatch has {mismatch.coef.shape[0]} signals; this simulator observes "
                f"{self.sim.n_obs}: estimate it with this designer (`Designer.mismatch`)"
            )
        return mismatch.arrays()

    def information(self, theta, obs, u, noise) -> np.ndarray:
        """[M, M] Fisher information of one episode's windows about the fitted parameters
        (their own units), white measurement noise of std `noise` [n_obs]."""
        j = self._jac(
            jnp.asarray(theta, jnp.float32),
            jnp.asarray(obs, jnp.float32),
            jnp.asarray(u, jnp.float32),
            jnp.asarray(1.0 / np.asarray(noise), jnp.float32),
        )
        j = np.asarray(j, np.float64)
        return j.T @ j

    def _sandwich_fn(self, theta, obs, u, noise, scale, mis=None, mean=None):
        """H [M, M] and B [M, (T+1) n_obs] of the fit's linearised estimator on one episode
        (windows weighted by 1 / scale, as the fit's normalized residuals are) under white
        measurement noise of std `noise`: the estimate moves by H^-1 B n for noise n.

        B = J^T dr/dn in closed form: noise n enters a window's residual
        r_i = w (pred_i(obs_s) - obs_(s+1+i)) through its measured initial state (the window's
        sensitivity P_i = d pred_i / d obs_s) and through its targets (minus the identity);
        the term dJ/dn r is zero on the model's own trajectory (r = 0). One forward-mode
        Jacobian per window, over the parameters and the initial state together, so the
        design's gradient is a second derivative of the simulator, not a third (a reverse
        derivative of J^T r through the windows was one order more and twice the program;
        on the Furuta it overflowed the stack of XLA's compiler).

        `mis` (`Mismatch.arrays`): a law mismatch, a white disturbance d_t of each step of
        state-dependent std, adds columns to B: it enters the windows' targets
        y_(s+1+i) = ... + sum_(j<=i) Phi(s+1+i <- s+1+j) d_(s+j), Phi the model's state
        transition, so d_t pulls the fit's gradient by -sum over the windows holding it of
        L_j = sum_(i>=j) Phi^T w J_i, accumulated backwards through the one-step Jacobians
        A_t (L_j = w J_j + A_(s+1+j)^T L_(j+1)): no more derivatives of the simulator than
        the sensor noise's.

        `mean` (`MismatchMean.arrays`): a law mismatch's mean m(x, u) along this trajectory;
        then also g [M], its pull on the fit's gradient, sum_t B_d,t m_t (the same adjoint):
        the estimate shifts by -H^-1 g (`_shift`)."""
        model, k, m = self.model, self.horizon, len(self.slots)
        weight = 1.0 / scale
        slots = jnp.asarray(self.slots)
        starts = jnp.asarray(self.starts)
        empty = jnp.zeros((0, u.shape[-1]), u.dtype)

        def one(s):
            u_w = jax.lax.dynamic_slice_in_dim(u, s, k)

            def pred(values, x):
                return model.window(model.params(theta.at[slots].set(values)), x, empty, u_w)

            jt, jx = jax.jacfwd(pred, argnums=(0, 1))(theta[slots], obs[s])
            return jt * weight[None, :, None], jx * weight[None, :, None]  # [k, n_obs, M|n_obs]

        jt, jx = jax.vmap(one)(starts)  # [W, k, n_obs, M], [W, k, n_obs, n_obs]
        h = jnp.einsum("wkom,wkon->mn", jt, jt)
        into_start = jnp.einsum("wkom,wkop->wmp", jt, jx) * noise  # [W, M, n_obs]
        into_target = -jt * (weight * noise)[None, None, :, None]  # [W, k, n_obs, M]
        b = jnp.zeros((obs.shape[0], obs.shape[1], m), jt.dtype)
        b = b.at[starts].add(jnp.swapaxes(into_start, 1, 2))
        b = b.at[starts[:, None] + 1 + jnp.arange(k)[None, :]].add(into_target)
        b = jnp.moveaxis(b, -1, 0).reshape(m, -1)
        if mis is None and mean is None:
            return h, b
        pulls, at = self._disturbance_pulls(theta, obs, u, jt, weight)
        if mis is not None:
            std = _mismatch_std(obs[:-1], u, self.sim.nq, mis)  # [T, n_obs]
            b = jnp.concatenate([b, self._pull_columns(pulls, at, std)], 1)
        if mean is None:
            return h, b
        drift = _mean_features(obs[:-1], u, *mean[1:]) @ mean[0].T  # [T, n_obs]
        return h, b, -jnp.einsum("wkom,wko->m", pulls, drift[at])

    def _pull_columns(self, pulls, at, std):
        """[M, T n_obs] the fit's gradient's pull by a unit of each step's disturbance times
        its std [T, n_obs] (`_sandwich_fn`)."""
        bp = jnp.zeros((std.shape[0], std.shape[1], pulls.shape[-1]), pulls.dtype)
        bp = bp.at[at].add(-pulls * std[at][..., None])
        return jnp.moveaxis(bp, -1, 0).reshape(pulls.shape[-1], -1)

    def _disturbance_pulls(self, theta, obs, u, jt, weight):
        """The fit's gradient's response to a disturbance of the step s + j inside each window
        (`_sandwich_fn`), [W, k, n_obs, M], and those steps [W, k]; jt [W, k, n_obs, M] the
        windows' weighted sensitivities."""
        model, k, n_obs = self.model, self.horizon, obs.shape[-1]
        params = model.params(theta)
        empty = jnp.zeros((0, u.shape[-1]), u.dtype)

        def one_step(x, ut):
            return model.window(params, x, empty, ut[None])[0]

        a = jax.vmap(jax.jacfwd(one_step))(obs[:-1], u)  # [T, n_obs, n_obs]: A_t
        a = jnp.concatenate([a, jnp.zeros((1, n_obs, n_obs), a.dtype)])  # the last unused
        wjt = jt * weight[None, None, :, None]  # d(fit's gradient) / d(target), sign aside
        starts = jnp.asarray(self.starts)

        def adjoint(s, wj):
            a_next = jax.lax.dynamic_slice_in_dim(a, s + 1, k)  # A_(s+1+j), j = 0..k-1

            def back(later, xs):
                wj_j, a_j = xs
                now = wj_j + a_j.T @ later
                return now, now

            return jax.lax.scan(back, jnp.zeros_like(wj[0]), (wj, a_next), reverse=True)[1]

        pulls = jax.vmap(adjoint)(starts, wjt)  # [W, k, n_obs, M]
        return pulls, starts[:, None] + jnp.arange(k)[None, :]  # the disturbance's step s + j

    def _parts(self, theta, ff, gain, x_ref, x0s, low, high, noise, mis, mean):
        """Per episode on average over the initial states x0s [S, n_obs]: H [M, M] and
        B B^T [M, M] of the fit's estimator (sensor noise and the law mismatch `mis`), g [M]
        the pull of the mismatch's mean `mean`; and the trajectories [S, T+1, n_obs],
        [S, T, n_act]."""
        obs, u = jax.vmap(lambda x0: self._rollout_fn(theta, ff, gain, x_ref, x0, low, high))(x0s)
        flat = obs.reshape(-1, obs.shape[-1])
        std = flat.std(axis=0)
        scale = jnp.maximum(std, 1e-6 * std.max() + 1e-12)  # as the fit's `prepare` does
        h, b, g = jax.vmap(lambda o, a: self._sandwich_fn(theta, o, a, noise, scale, mis, mean))(
            obs, u
        )
        meat = jnp.einsum("smp,snp->smn", b, b)
        return h.mean(0), meat.mean(0), g.mean(0), obs, u

    def predicted_se(self, theta, design: Design, x0s, noise, mismatch=None) -> np.ndarray:
        """[M] one episode's standard errors of discovery's fit (measured initial states) of a
        record of this design from the initial states x0s [S, n_obs] (averaged over them),
        under the sensor noise and the law mismatch `mismatch` (a `Mismatch`; None: none)."""
        mis, mean = self._mis(mismatch), self._mean_arrays(None)
        h, meat, _ = self._predict(*_f32(*_rollout_args(theta, design, x0s), noise), mis, mean)
        return np.sqrt(np.maximum(np.diag(_covariance(h, meat)), 0.0))

    def predicted_shift(self, theta, design: Design, x0s, noise, mean: MismatchMean):
        """[M] the shift of one episode's estimate (any number of episodes of this design:
        it does not average away) that the law mismatch's mean `mean` drags it by, from the
        initial states x0s (averaged over them): -H^-1 g, the linearised estimator's response
        to m(x, u) along the predicted trajectory (`MismatchMean`)."""
        args = _f32(*_rollout_args(theta, design, x0s), noise)
        h, _, g = self._predict(*args, self._mis(None), self._mean_arrays(mean))
        return _shift(h, g)

    def _open_rollout(self, theta, u, x0):
        """[T+1, n_obs] the model's trajectory under the open-loop controls u [T, n_act]."""
        sim, params = self.sim, self.model.params(theta)
        state = sim.init(x0[: sim.nq], x0[sim.nq :], params)

        def step(state, ut):
            state = sim.step(params, state, ut)
            return state, sim.observe(params, state)

        return jnp.concatenate([x0[None], jax.lax.scan(step, state, u)[1]])

    def open_loop(self, estimate: dict | None, controls, x0) -> np.ndarray:
        """[T+1, n_obs] the trajectory the model predicts at `estimate` under the open-loop
        controls [T, n_act] from x0 [n_obs] (to check a signal against the limits)."""
        theta = jnp.asarray(self.theta(estimate), jnp.float32)
        return np.asarray(self._rollout_open(theta, *_f32(controls, x0)), np.float64)

    def _parts_open(self, theta, u, x0, noise, scale=None, mis=None, mean=None):
        """H and B B^T of one episode of the open-loop controls u [T, n_act] from x0, its
        residuals over `scale` (None: the episode's own std, a record of it repeated); with
        `mean`, also g, the mismatch mean's pull (before the trajectory)."""
        obs = self._open_rollout(theta, u, x0)
        if scale is None:
            std = obs.std(axis=0)
            scale = jnp.maximum(std, 1e-6 * std.max() + 1e-12)
        if mean is None:
            h, b = self._sandwich_fn(theta, obs, u, noise, scale, mis)
            return h, b @ b.T, obs
        h, b, g = self._sandwich_fn(theta, obs, u, noise, scale, mis, mean)
        return h, b @ b.T, g, obs

    def predicted_se_of(
        self, estimate: dict | None, controls, x0, noise, mismatch=None
    ) -> np.ndarray:
        """[M] one episode's standard errors of the fit on each of the open-loop records
        controls [E, T, n_act] from x0 [n_obs] (any signal: random steps, a PRBS, a design's
        controls), pooled over them as the fit's sandwich pools episodes (each weighted by
        the signals' std over all of them, as the fit weighs them); what a standard signal
        is predicted to give, on the same model and noise as a design's prediction (and the
        law mismatch `mismatch`, a `Mismatch`; None: sensor noise alone)."""
        u, theta, x0, noise, scale = self._open_records(estimate, controls, x0, noise)
        mis = self._mis(mismatch)
        h = meat = 0.0
        for ue in u:
            he, me, _ = self._predict_open(theta, *_f32(ue), x0, noise, scale, mis)
            h, meat = h + np.asarray(he, np.float64), meat + np.asarray(me, np.float64)
        return np.sqrt(np.maximum(np.diag(_covariance(h / len(u), meat / len(u))), 0.0))

    def _open_records(self, estimate: dict | None, controls, x0, noise):
        """Open-loop records controls [E, T, n_act] checked, the estimate's parameters, x0 and
        the noise as float32, and the signals' std over all records (the fit's weights)."""
        u = np.asarray(controls, np.float64)
        if u.ndim != 3 or u.shape[1:] != (self.steps, self.sim.n_act):
            raise ValueError(
                f"controls have shape {u.shape}; give [E, {self.steps}, {self.sim.n_act}]"
            )
        theta = jnp.asarray(self.theta(estimate), jnp.float32)
        x0, noise = _f32(x0, np.maximum(np.asarray(noise, np.float64), 1e-9))
        obs = np.concatenate([np.asarray(self._rollout_open(theta, *_f32(ue), x0)) for ue in u])
        std = obs.std(axis=0)
        scale = jnp.asarray(np.maximum(std, 1e-6 * std.max() + 1e-12), jnp.float32)
        return u, theta, x0, noise, scale

    def drag_of(self, estimate: dict | None, controls, x0, noise, mean: MismatchMean) -> dict:
        """What the law mismatch's mean `mean` (`MismatchMean`) does to the fit of the
        open-loop records controls [E, T, n_act] from x0 [n_obs] pooled (each episode weighted
        as the fit weighs them): "shift" [M], the pooled estimate's shift -H^-1 sum_e g_e
        (H summed over the episodes, g_e each episode's pull); "se" [M], one episode's standard
        error of the fit's cluster-robust noise part, sensor noise plus the episodes' drags'
        scatter: at the pooled estimate each episode's gradient is g_e + H_e shift (they sum to
        nil), and episodes of different signals, dragged apart, count as scatter; one signal
        repeated from one state adds nothing. Both in the parameters' own units."""
        u, theta, x0, noise, scale = self._open_records(estimate, controls, x0, noise)
        mean_args = self._mean_arrays(mean)
        parts = [
            self._predict_open(theta, *_f32(ue), x0, noise, scale, None, mean_args)[:3] for ue in u
        ]
        hs, meats, gs = (np.stack([np.asarray(p[i], np.float64) for p in parts]) for i in range(3))
        h = hs.sum(0)
        shift = _shift(h, gs.sum(0))
        grads = gs + hs @ shift  # [E, M] each episode's gradient at the pooled estimate
        meat = meats.sum(0) + grads.T @ grads
        cov = _covariance(h, meat) * len(u)  # one episode's
        return {"shift": shift, "se": np.sqrt(np.maximum(np.diag(cov), 0.0))}

    def _noise_loss_fn(self, theta, obs, u, noise, scale):
        """The sum over one episode's windows of the squared residuals (each over `scale`)
        that white sensor noise of std `noise` alone leaves the fit in expectation: a
        window's residual r_i = P_i n_s - n_(s+1+i) holds the noise of its measured initial
        state (P_i its prediction's sensitivity to that state) besides its targets'."""
        model, k = self.model, self.horizon
        params = model.params(theta)
        empty = jnp.zeros((0, u.shape[-1]), u.dtype)

        def one(s):
            u_w = jax.lax.dynamic_slice_in_dim(u, s, k)
            jx = jax.jacfwd(lambda x: model.window(params, x, empty, u_w))(obs[s])
            return jnp.sum((jx * noise[None, None, :] / scale[None, :, None]) ** 2)

        start = jnp.sum(jax.vmap(one)(jnp.asarray(self.starts)))
        return start + len(self.starts) * k * jnp.sum((noise / scale) ** 2)

    def noise_loss(self, theta, obs, u, noise, scale) -> float:
        """The fit's mean squared normalized residual that sensor noise alone would leave on
        the records obs [E, T+1, n_obs], u [E, T, n_act] (the fit's `scale` [n_obs]): the
        floor above which a residual is law mismatch. With measured initial states it is
        more than the targets' noise (sum of (noise / scale)^2 / n_obs): each window's
        initial state carries noise too, which its prediction propagates."""
        total = 0.0
        args = _f32(theta, np.maximum(np.asarray(noise, np.float64), 0.0), scale)
        for o, a in zip(np.asarray(obs), np.asarray(u), strict=True):
            total += float(self._noise_loss(args[0], *_f32(o, a), *args[1:]))
        return total / (len(obs) * len(self.starts) * self.horizon * self.sim.n_obs)

    def _record_fn(self, theta, obs, u, noise, scale, mis):
        """H and B B^T of one recorded episode, its residuals over `scale`."""
        h, b = self._sandwich_fn(theta, obs, u, noise, scale, mis)
        return h, b @ b.T

    def record_se(self, theta, obs, u, noise, mismatch=None) -> np.ndarray:
        """[M] standard errors of the fit's estimate at theta on the records obs [E, T+1, n_obs]
        of controls u [E, T, n_act] (all E together) if their residuals were white sensor
        noise of std `noise` [n_obs] alone: the sandwich H^-1 B B^T H^-1 on the recorded
        trajectories. The design's prediction made on the record the plant gave: against the
        fit's cluster-robust noise part (the episodes' own gradients' scatter) it tells the
        sensor noise's share from a law mismatch that differs between episodes. With
        `mismatch` (a `Mismatch`) the residuals hold its disturbance too."""
        obs, u = np.asarray(obs, np.float64), np.asarray(u, np.float64)
        e = len(obs)
        if obs.shape != (e, self.steps + 1, self.sim.n_obs) or u.shape != (
            e,
            self.steps,
            self.sim.n_act,
        ):
            raise ValueError(
                f"obs {obs.shape} and u {u.shape}: give [E, {self.steps + 1}, {self.sim.n_obs}] "
                f"and [E, {self.steps}, {self.sim.n_act}] (this designer's record length)"
            )
        # every episode weighted as the fit weighs them all: by each signal's std over the
        # records together (an episode's own std would weigh a quiet episode up)
        std = obs.reshape(-1, obs.shape[-1]).std(axis=0)
        scale = np.maximum(std, 1e-6 * std.max() + 1e-12)
        fixed = _f32(theta, np.maximum(np.asarray(noise, np.float64), 1e-9), scale)
        mis = self._mis(mismatch)
        h = meat = 0.0
        for o, a in zip(obs, u, strict=True):
            he, me = self._record(fixed[0], *_f32(o, a), *fixed[1:], mis)
            h, meat = h + np.asarray(he, np.float64), meat + np.asarray(me, np.float64)
        return np.sqrt(np.maximum(np.diag(_covariance(h, meat)), 0.0))

    def trajectory(self, theta, design: Design, x0s) -> tuple[np.ndarray, np.ndarray]:
        """The predicted trajectories [S, T+1, n_obs] and controls [S, T, n_act] from x0s."""
        obs, u = jax.vmap(self._rollout, in_axes=(None,) * 4 + (0, None, None))(
            *_f32(*_rollout_args(theta, design, x0s))
        )
        return np.asarray(obs, np.float64), np.asarray(u, np.float64)

    # -- the design -----------------------------------------------------------------------

    def _objective(
        self,
        wave,
        theta,
        noise,
        mis,
        mean,
        bias_weight,
        ref,
        pick,
        amplitude,
        middle,
        gain,
        x_ref,
        x0s,
        lim,
    ):
        """The criterion plus the limits' penalty of the feedforward middle + amplitude x wave
        (wave [T, n_act] in [-1, 1]); also the criterion alone and the trajectories and
        controls [S, ...], to keep the best iterate that keeps the limits. The criterion's
        covariance is the mean squared error of `bias_weight` episodes (times them):
        H^-1 (B B^T + bias_weight g g^T) H^-1, the mismatch mean's drag not averaging away."""
        h, meat, g, obs, u = self._parts(
            theta, middle + amplitude * wave, gain, x_ref, x0s, lim[0], lim[1], noise, mis, mean
        )
        value = _traced_criterion(h, meat + bias_weight * jnp.outer(g, g), ref, pick)
        return value + PENALTY * _penalty(obs, lim) / x0s.shape[0], (value, obs, u)

    def _optimiser(self, parameterisation: str, learning_rate: float):
        """Adam and its compiled step for a parameterisation at a learning rate: per step, the
        variables are w itself, projected back into [-1, 1] after every update; Fourier, the
        coefficients, w their series through tanh. Every estimate, noise, limit, feedback and
        initial state is a traced argument, so each later design reuses the program."""
        key = (parameterisation, float(learning_rate))
        if key not in self._steps:
            optimiser = optax.adam(learning_rate)
            if parameterisation == "fourier":

                def wave(c):
                    return _feedforward(c, self.frequencies, self.dt, self.steps)

                def project(c):
                    return c
            else:

                def wave(v):
                    return v

                def project(v):
                    return jnp.clip(v, -1.0, 1.0)

            def step(p, opt_state, *args):
                (total, (value, obs, u)), grad = jax.value_and_grad(
                    lambda p: self._objective(wave(p), *args), has_aux=True
                )(p)
                updates, opt_state = optimiser.update(jnp.nan_to_num(grad), opt_state)
                p_new = project(optax.apply_updates(p, updates))
                return p_new, opt_state, total, value, obs, u

            self._steps[key] = (optimiser, jax.jit(step))
        return self._steps[key]

    def _adam(self, parameterisation, learning_rate, p0, iterations, args, limits: Limits):
        """Adam from p0. Returns the best iterate that keeps the joints' and speed limits on
        the model's trajectories (None if none did) and its criterion, the best iterate by the
        penalised objective (the fallback, shrunk by `finish`), and the criterion per
        iteration. The values are the iterate's before its update."""
        optimiser, step = self._optimiser(parameterisation, learning_rate)
        p = jnp.asarray(p0, jnp.float32)
        opt_state = optimiser.init(p)
        kept, kept_value, fallback, fallback_total, history = None, np.inf, p, np.inf, []
        for _ in range(int(iterations)):
            p_new, opt_state, total, value, obs, u = step(p, opt_state, *args)
            value, total = float(value), float(total)
            history.append(value)
            if np.isfinite(total) and total < fallback_total:
                fallback, fallback_total = p, total
            if np.isfinite(value) and value < kept_value:
                # the controls are clipped to the bound by construction; check what is not
                bad = limits.violation(np.asarray(obs, np.float64), np.asarray(u, np.float64))
                if max(bad["joint"], bad["speed"]) <= 0:
                    kept, kept_value = p, value
            p = p_new
        return kept, kept_value, fallback, history

    def _first_value(self, parameterisation, learning_rate, p0, args) -> float:
        """The penalised objective at p0 (one step of the compiled optimiser: no other program)."""
        optimiser, step = self._optimiser(parameterisation, learning_rate)
        p = jnp.asarray(p0, jnp.float32)
        total = float(step(p, optimiser.init(p), *args)[2])
        return total if np.isfinite(total) else np.inf

    def design(
        self,
        estimate: dict | None,
        x0,
        noise,
        limits: Limits,
        criterion: str = "D",
        iterations: int | None = None,
        learning_rate: float | None = None,
        gain=None,
        x_ref=None,
        seed: int = 0,
        start: Design | None = None,
        rivals: dict | None = None,
        parameterisation: str = "per_step",
        mismatch: Mismatch | None = None,
        mismatch_mean: MismatchMean | None = None,
        episodes: float = 1.0,
    ) -> Design:
        """Optimise the excitation at `estimate` ({key: {param: value}}; missing: the
        simulator's own value) for episodes from the initial state x0 [n_obs] (or the
        expectation over initial states [S, n_obs], e.g. draws of the task's); `noise` [n_obs]
        the measurement noise std (None: 1% of each signal's std along a first trajectory);
        `gain` [n_act, n_obs] a stabilising feedback about x_ref (default the first x0);
        `start` a previous design to continue from (a sequential design's last round);
        `rivals` {name: controls [T, n_act]} open-loop signals of the same bound (random
        steps, a PRBS): where the model predicts one of them better by the criterion (and it
        keeps the limits), the Design carries its controls and its name in `signal`, so a
        design is never worse, on the model, than the standard signals it was offered.

        `parameterisation`: "per_step" (default) makes every step's feedforward a variable
        in the bound, optimised from the best on the model (the penalised criterion) of:
        `start`'s signal, each rival within the bound, and a random smooth wave (a tanh
        Fourier series of `seed`); "fourier" optimises a tanh Fourier series's coefficients
        (from `start`'s, else random ones). `iterations` and `learning_rate` default per
        parameterisation (ITERATIONS, LEARNING_RATE).

        `mismatch` (a `Mismatch`, e.g. `Designer.mismatch` of the records so far, `calibrated`
        to the fit's noise part): the criterion's covariance holds its disturbance besides the
        sensor noise, so the design seeks information where the parameters' sensitivities
        stand out of the law mismatch (e.g. away from a friction's reversals, where the
        plant's law differs most), and the prediction holds it. None: sensor noise alone.

        `mismatch_mean` (a `MismatchMean`, e.g. `Designer.mismatch_mean` of the records so
        far): the criterion is the mean squared error of `episodes` episodes, the shift the
        mismatch's mean drags each episode's estimate by (`predicted_shift`, which does not
        average away) squared beside the variance (which does): H^-1 (B B^T + episodes g g^T)
        H^-1, so the design prefers signals whose estimate the mismatch does not drag.
        `Design.predicted_shift` holds that shift. None: no shift."""
        if not episodes > 0:
            raise ValueError(f"episodes = {episodes} must be positive (the bias term's weight)")
        if parameterisation not in PARAMETERISATIONS:
            raise ValueError(
                f"parameterisation {parameterisation!r} is unknown: choose one of "
                f"{list(PARAMETERISATIONS)}"
            )
        sim = self.sim
        x0s = np.atleast_2d(np.asarray(x0, np.float64))
        if x0s.ndim != 2 or x0s.shape[1] != sim.n_obs:
            raise ValueError(
                f"x0 has shape {np.shape(x0)}; give a state [{sim.n_obs}] or states "
                f"[S, {sim.n_obs}]"
            )
        pick = _pick(criterion, self.labels)
        iterations = ITERATIONS[parameterisation] if iterations is None else int(iterations)
        learning_rate = float(learning_rate or LEARNING_RATE[parameterisation])
        if iterations < 1:
            raise ValueError(f"iterations = {iterations} must be at least 1")
        theta = self.theta(estimate)
        ref = self.reference(theta)
        middle = 0.5 * (limits.u_low + limits.u_high)
        amplitude = 0.5 * (limits.u_high - limits.u_low)
        gain = np.zeros((sim.n_act, sim.n_obs)) if gain is None else np.asarray(gain, np.float64)
        if gain.shape != (sim.n_act, sim.n_obs):
            raise ValueError(
                f"gain has shape {gain.shape}; it must be [n_act, n_obs] = {[sim.n_act, sim.n_obs]}"
            )
        x_ref = x0s[0] if x_ref is None else np.asarray(x_ref, np.float64)
        rng = np.random.default_rng(seed)
        c_random = rng.normal(
            0.0, 1.0 / math.sqrt(len(self.frequencies)), (sim.n_act, 2 * len(self.frequencies))
        )
        wave_random = np.asarray(
            _feedforward(c_random, self.frequencies, self.dt, self.steps), np.float64
        )
        lim = (limits.u_low, limits.u_high, limits.q_low, limits.q_high, limits.max_speed)
        if noise is None:
            obs, _ = self._rollout(
                *_f32(theta, middle + amplitude * wave_random, gain, x_ref, x0s[0], *lim[:2])
            )
            noise = 0.01 * np.maximum(np.asarray(obs).std(axis=0), 1e-9)
        noise = np.maximum(np.asarray(noise, np.float64), 1e-9)
        pick32 = None if pick is None else jnp.asarray(pick, jnp.float32)
        mis, mean = self._mis(mismatch), self._mean_arrays(mismatch_mean)
        weight = float(episodes) if mismatch_mean is not None else 0.0
        args = (
            *_f32(theta, noise),
            mis,
            mean,
            *_f32(weight, ref),
            pick32,
            *_f32(amplitude, middle, gain, x_ref, x0s),
            _f32(*lim),
        )
        if parameterisation == "fourier":
            has = start is not None and start.coefficients is not None
            p0 = np.asarray(start.coefficients, np.float64) if has else c_random
        else:
            # the starts, in units of this design's bound: a last design's own signal (a rival
            # it recorded, or its feedforward with the swing it kept), the rivals, a smooth one
            starts = {"random": wave_random}
            if start is not None:
                last = start.planned_controls if start.signal != "designed" else None
                last = start.feedforward() if last is None else last
                starts["start"] = last
            for name, u in (rivals or {}).items():
                starts[f"rival {name}"] = np.asarray(u, np.float64)
            for name in [k for k in starts if k != "random"]:
                u = np.asarray(starts[name], np.float64)
                if u.shape != (self.steps, sim.n_act):
                    raise ValueError(
                        f"{name} has shape {u.shape}; give [{self.steps}, {sim.n_act}]"
                    )
                starts[name] = np.clip((u - middle) / np.maximum(amplitude, 1e-12), -1.0, 1.0)
            scores = {
                k: self._first_value(parameterisation, learning_rate, w, args)
                for k, w in starts.items()
            }
            p0 = starts[min(scores, key=scores.get)]
        kept, _, fallback, history = self._adam(
            parameterisation, learning_rate, p0, iterations, args, limits
        )
        best = np.asarray(fallback if kept is None else kept, np.float64)
        design = Design(
            coefficients=best if parameterisation == "fourier" else None,
            amplitude=amplitude,
            middle=middle,
            frequencies=self.frequencies,
            dt=self.dt,
            steps=self.steps,
            gain=gain,
            x_ref=x_ref,
            angular=self.angular,
            limits=limits,
            keys=list(self.labels),
            predicted_se=np.full(len(self.slots), np.inf),
            trajectory=np.zeros((self.steps + 1, sim.n_obs)),
            planned_controls=np.zeros((self.steps, sim.n_act)),
            criterion=str(criterion),
            history=history,
            waveform=best if parameterisation == "per_step" else None,
        )
        design = self.finish(
            design, theta, x0s, noise, mismatch=mismatch, mismatch_mean=mismatch_mean
        )
        if rivals:
            design = self._against(
                design, rivals, theta, x0s[0], noise, ref, pick, mis, mean, weight
            )
        return design

    def _against(
        self, design: Design, rivals: dict, theta, x0, noise, ref, pick, mis, mean, weight
    ) -> Design:
        """The design, or the rival signal of least criterion on the model (open loop, from
        x0, keeping the limits)."""
        if np.any(design.gain != 0):
            raise ValueError("rivals are open-loop signals: give them to an open-loop design")
        args = _f32(*_rollout_args(theta, design, x0[None]), noise)
        h, meat, g = self._predict(*args, mis, mean)
        best = _criterion_value(_mse(h, meat, g, weight), ref, pick)
        theta32, x032, noise32 = _f32(theta, x0, noise)
        for name, u in rivals.items():
            u = np.asarray(u, np.float64)
            if u.shape != (self.steps, self.sim.n_act):
                raise ValueError(
                    f"rival {name!r} has shape {u.shape}; give [{self.steps}, {self.sim.n_act}]"
                )
            if (u > design.limits.u_high + 1e-9).any() or (u < design.limits.u_low - 1e-9).any():
                continue  # beyond the amplitude bound: no fair rival
            value, (h, meat, g, obs) = self._open_criterion(
                theta32, u, x032, noise32, ref, pick, mis, mean, weight
            )
            if max(design.limits.violation(np.asarray(obs), u).values()) > 0:
                continue
            if value < best:
                best = value
                design.signal, design.planned_controls = name, u
                design.trajectory = np.asarray(obs, np.float64)
                cov = _covariance(h, meat)
                design.predicted_se = np.sqrt(np.maximum(np.diag(cov), 0.0))
                if design.predicted_shift is not None:
                    design.predicted_shift = _shift(h, g)
        return design

    def _open_criterion(self, theta, u, x0, noise, ref, pick, mis, mean, weight):
        """The design's criterion of one episode of open-loop controls u [T, n_act] from x0
        (`_mse`: with the mismatch mean's drag over `weight` episodes), and its parts
        H, B B^T, g and the trajectory."""
        h, meat, g, obs = self._predict_open(theta, *_f32(u), x0, noise, mis=mis, mean=mean)
        return _criterion_value(_mse(h, meat, g, weight), ref, pick), (h, meat, g, obs)

    def criterion_of(
        self,
        estimate: dict | None,
        controls,
        x0,
        noise,
        criterion="D",
        mismatch: Mismatch | None = None,
        mismatch_mean: MismatchMean | None = None,
        episodes: float = 1.0,
    ) -> float:
        """The value of `design`'s criterion (lower is better) for one episode of the open-loop
        controls [T, n_act] from x0 [n_obs] at `estimate`: how `design` ranks a signal against
        its rivals, with the same `mismatch`, `mismatch_mean` and `episodes` (the mean squared
        error's bias weight)."""
        u = np.asarray(controls, np.float64)
        if u.shape != (self.steps, self.sim.n_act):
            raise ValueError(
                f"controls have shape {u.shape}; give [{self.steps}, {self.sim.n_act}]"
            )
        theta = self.theta(estimate)
        weight = float(episodes) if mismatch_mean is not None else 0.0
        return self._open_criterion(
            *_f32(theta),
            u,
            *_f32(x0, np.maximum(np.asarray(noise, np.float64), 1e-9)),
            self.reference(theta),
            _pick(criterion, self.labels),
            self._mis(mismatch),
            self._mean_arrays(mismatch_mean),
            weight,
        )[0]

    def per_step(
        self,
        estimate: dict | None,
        x0,
        noise,
        limits: Limits,
        criterion="D",
        iterations: int = 300,
        restarts: int = 4,
        learning_rate: float = 0.05,
        seed: int = 0,
        starts: dict | None = None,
        mismatch: Mismatch | None = None,
    ) -> dict:
        """The most flexible open-loop excitation: every step's control a free variable in the
        amplitude bound (projected Adam on the criterion, the joints' and speed limits as
        penalties), from each of `starts` ({name: controls [T, n_act]}, e.g. the standard
        signals) and `restarts` random starts; the best iterate that keeps every limit on the
        model's trajectory. No smoothness and no harmonic limit: a search for how much any
        open-loop signal of this bound could carry (`design`'s Fourier series is a subset).
        Returns {"controls", "trajectory", "predicted_se" (one episode), "value" (the
        criterion, as `design` scores its rivals), "start" (the winning start's name),
        "history" (the winning run's criterion per iteration)}."""
        sim = self.sim
        x0 = np.asarray(x0, np.float64)
        if x0.shape != (sim.n_obs,):
            raise ValueError(f"x0 has shape {x0.shape}; give a state [{sim.n_obs}]")
        if int(iterations) < 1 or int(restarts) < 0 or not (starts or restarts):
            raise ValueError(
                f"iterations = {iterations} >= 1 and restarts = {restarts} >= 0, with at least "
                "one start (restarts > 0 or starts)"
            )
        pick = _pick(criterion, self.labels)
        theta = self.theta(estimate)
        ref = self.reference(theta)
        middle = 0.5 * (limits.u_low + limits.u_high)
        amplitude = 0.5 * (limits.u_high - limits.u_low)
        noise = np.maximum(np.asarray(noise, np.float64), 1e-9)
        inits = {}
        for name, u in (starts or {}).items():
            u = np.asarray(u, np.float64)
            if u.shape != (self.steps, sim.n_act):
                raise ValueError(
                    f"start {name!r} has shape {u.shape}; give [{self.steps}, {sim.n_act}]"
                )
            inits[name] = np.clip((u - middle) / np.maximum(amplitude, 1e-12), -1.0, 1.0)
        rng = np.random.default_rng(seed)
        for r in range(int(restarts)):
            inits[f"random {r}"] = np.clip(rng.normal(0.0, 0.5, (self.steps, sim.n_act)), -1, 1)
        lim = (limits.u_low, limits.u_high, limits.q_low, limits.q_high, limits.max_speed)
        pick32 = None if pick is None else jnp.asarray(pick, jnp.float32)
        gain = np.zeros((sim.n_act, sim.n_obs))  # open loop
        mis = self._mis(mismatch)
        args = (
            *_f32(theta, noise),
            mis,
            self._mean_arrays(None),
            *_f32(0.0, ref),
            pick32,
            *_f32(amplitude, middle, gain, x0, x0[None]),
            _f32(*lim),
        )
        best = {"value": np.inf}
        for name, v0 in inits.items():
            kept, value, _, history = self._adam(
                "per_step", float(learning_rate), v0, iterations, args, limits
            )
            if kept is not None and value < best["value"]:
                u = middle + amplitude * np.asarray(kept, np.float64)
                best = {"value": value, "controls": u, "start": name, "history": history}
        if "controls" not in best:
            raise ValueError(
                "no per-step excitation kept the limits from this initial state: it starts "
                "outside them, or the limits leave no room to move; widen them"
            )
        h, meat, obs = self._predict_open(*_f32(theta, best["controls"], x0, noise), mis=mis)
        best["trajectory"] = np.asarray(obs, np.float64)
        best["predicted_se"] = np.sqrt(np.maximum(np.diag(_covariance(h, meat)), 0.0))
        return best

    def finish(
        self,
        design: Design,
        theta,
        x0s,
        noise,
        shrink: float = 0.8,
        tries: int = 30,
        mismatch=None,
        mismatch_mean=None,
    ):
        """Shrink the feedforward's swing until the predicted trajectories keep every limit,
        then fill in the trajectory (from the first initial state) and the predicted
        standard errors."""
        x0s = np.atleast_2d(np.asarray(x0s, np.float64))
        for _ in range(tries):
            obs, u = self.trajectory(theta, design, x0s)
            bad = design.limits.violation(obs, u)
            if max(bad["joint"], bad["speed"]) <= 0:
                break
            design.amplitude = design.amplitude * shrink
        else:
            raise ValueError(
                f"no excitation keeps the limits from these initial states (excess {bad}): "
                "a state starts outside them or the feedback cannot hold the system; "
                "widen the limits or give a stabilising feedback"
            )
        design.trajectory, design.planned_controls = obs[0], u[0]
        design.predicted_se = self.predicted_se(theta, design, x0s, noise, mismatch)
        if mismatch_mean is not None:
            design.predicted_shift = self.predicted_shift(theta, design, x0s, noise, mismatch_mean)
        return design


def calibrated(
    designer: Designer,
    mismatch: Mismatch,
    theta,
    obs,
    u,
    noise,
    noise_half,
    level: float = 0.95,
    min_episodes: int = 4,
) -> Mismatch:
    """`mismatch` scaled so that, on the records it was estimated from (obs [E, T+1, n_obs],
    u [E, T, n_act], the fit's theta and sensor noise), the sandwich of the sensor noise and
    its disturbance gives the fit's noise part `noise_half` [M] (t x cluster-robust se, a
    typical draw of E clusters: over `typical_scale(E)`): the mismatch as discovery's fit sees
    it. A white disturbance of the one-step residuals' size is the model; a plant's law
    mismatch persists over steps (a friction's error while sliding one way), so its windows'
    residuals grow faster and the fit's scatter is larger than a white one of the same step
    size gives: one factor over the parameters (their relative variances pooled) takes that
    up. The factor is a ratio of variances with the fit's noise part's degrees of freedom
    (E - 1): below `min_episodes` episodes (2: a single draw, a factor anywhere from nil to
    several times) the mismatch is returned as estimated (factor 1), the one-step residuals'
    size being the better measure then."""
    episodes = len(obs)
    if episodes < min_episodes:
        return dataclasses.replace(mismatch, scale=1.0)
    sensor = designer.record_se(theta, obs, u, noise) ** 2
    white = designer.record_se(theta, obs, u, noise, mismatch.scaled(1.0 / mismatch.scale)) ** 2
    t = stats.t.ppf(0.5 + level / 2, episodes - 1)
    fit = (np.asarray(noise_half, np.float64) / t / typical_scale(episodes)) ** 2
    ref = np.maximum(np.abs(np.asarray(theta, np.float64)[designer.slots]), 1e-30) ** 2
    ok = np.isfinite(fit) & np.isfinite(white) & np.isfinite(sensor)
    extra = np.sum(((white - sensor) / ref)[ok])
    factor = np.sum((np.maximum(fit - sensor, 0.0) / ref)[ok]) / extra if extra > 0 else 0.0
    return dataclasses.replace(mismatch, scale=float(factor))


def with_mismatch(
    predicted_half,
    episodes: int,
    sensor_half,
    noise_half,
    half,
    episodes_before: int,
    level: float = 0.95,
    noise_predicted=None,
) -> tuple[np.ndarray, np.ndarray]:
    """The fit's noise part and reported half-widths [M] for a record of `episodes` episodes
    whose sensor-noise half-widths the design predicts (`predicted_half`, typical ones:
    `half_width`, e.g. of every round's controls so far at the current estimate and noise),
    from what the fit of the
    `episodes_before` episodes recorded so far measured: their sensor part on the record
    (`Designer.record_se` as a half-width), the fit's noise part (t x cluster-robust se) and
    its reported half-width (noise part plus law-mismatch part, `confidence_intervals`).

    A law mismatch enters the fit's intervals twice, and the design's prediction (sensor
    noise on the model) holds neither: (1) where it differs between episodes the
    cluster-robust noise part counts it as scatter, so the noise part is the sensor part
    times noise_half / sensor_half as measured so far (that fit's noise part a typical draw
    of E_before clusters: divided by `typical_scale(E_before)`); (2) its systematic part,
    sqrt(misfit (H^-1)_jj), does not average away: the misfit (a sum over the record) grows
    with the episodes while H^-1 shrinks as the predicted information grows, so it is carried
    from the fit so far as sqrt(E / E_before) x (predicted se / sensor se so far). The
    view-disagreement part is carried the same way (a shift, not scatter). Before any data
    (episodes_before = 0) there is nothing to carry: the sensor part is returned for both.

    `noise_predicted` [M]: the noise part predicted with a model of the mismatch's scatter
    (`Designer.predicted_se_of(..., mismatch=)` as a half-width): it replaces (1), which
    carries the scatter of the signals recorded so far to a signal that may differ; (2) is
    carried as above."""
    pred = np.asarray(predicted_half, np.float64)
    if episodes_before == 0:
        first = pred if noise_predicted is None else np.asarray(noise_predicted, np.float64)
        return first.copy(), first.copy()
    if episodes_before < 2 or episodes < 2:
        raise ValueError(
            f"episodes_before = {episodes_before} and episodes = {episodes}: intervals need "
            "at least 2 episodes (episodes_before = 0: nothing recorded yet)"
        )
    sensor, noise, full = (np.asarray(x, np.float64) for x in (sensor_half, noise_half, half))
    with np.errstate(invalid="ignore", divide="ignore"):
        # the fit's noise part so far is a typical draw of E_before clusters (`typical_scale`)
        # over the sensor part (the sandwich on the record, no draw): the scatter of the true
        # errors over the sensor noise's is that over typical_scale(E_before)
        scatter = np.where(sensor > 0, noise / sensor, 1.0) / typical_scale(episodes_before)
        # standard errors without the t quantiles and typical scales of the two amounts
        t_before = stats.t.ppf(0.5 + level / 2, episodes_before - 1)
        t_now = stats.t.ppf(0.5 + level / 2, episodes - 1) * typical_scale(episodes)
        shrink = np.where(sensor > 0, (pred / t_now) / (sensor / t_before), 1.0)
    noise_now = pred * scatter
    if noise_predicted is not None:
        noise_now = np.asarray(noise_predicted, np.float64)
    bias = np.maximum(full - noise, 0.0) * math.sqrt(episodes / episodes_before) * shrink
    return noise_now, noise_now + bias


def _rollout_args(theta, design: Design, x0s) -> tuple:
    """The arguments of a design's compiled rollout, in its order (x0s the batched one)."""
    return (
        theta,
        design.feedforward(),
        design.gain,
        design.x_ref,
        x0s,
        design.limits.u_low,
        design.limits.u_high,
    )


def _covariance(h, meat) -> np.ndarray:
    """[M, M] the fit's per-episode covariance H^-1 B B^T H^-1."""
    inv = np.linalg.pinv(np.asarray(h, np.float64))
    return inv @ np.asarray(meat, np.float64) @ inv


def _shift(h, g) -> np.ndarray:
    """[M] the linearised estimator's shift -H^-1 g under a pull g of its gradient."""
    return -np.linalg.pinv(np.asarray(h, np.float64)) @ np.asarray(g, np.float64)


def _mse(h, meat, g, weight) -> np.ndarray:
    """[M, M] `weight` episodes' mean squared error times them: H^-1 (B B^T + w g g^T) H^-1."""
    g = np.asarray(g, np.float64)
    return _covariance(h, np.asarray(meat, np.float64) + float(weight) * np.outer(g, g))


def _criterion_value(cov, ref, pick) -> float:
    """The design's criterion on a covariance (parameters in units of their size, `ref`)."""
    rel = cov / np.outer(ref, ref)
    if pick is None:
        return float(np.linalg.slogdet(rel + RIDGE * np.trace(rel) * np.eye(len(rel)))[1])
    return float(np.log(np.sum(np.diag(rel) * pick) + EIVAL_FLOOR))


def _traced_criterion(h, meat, ref, pick):
    """The design's criterion on H and B B^T (traced; parameters in units of their size)."""
    m = h.shape[0]
    h = h / jnp.outer(ref, ref)
    meat = meat / jnp.outer(ref, ref)
    h = h + RIDGE * (jnp.trace(h) / m + EIVAL_FLOOR) * jnp.eye(m)
    meat = meat + RIDGE * (jnp.trace(meat) / m + EIVAL_FLOOR) * jnp.eye(m)
    if pick is None:  # D: log det of the covariance H^-1 B B^T H^-1
        return jnp.linalg.slogdet(meat)[1] - 2 * jnp.linalg.slogdet(h)[1]
    inv = jnp.linalg.inv(h)  # A (pick all ones) or one parameter's variance (a one-hot pick)
    return jnp.log(jnp.sum(jnp.diag(inv @ meat @ inv) * pick))


def _mismatch_std(obs, u, nq, mis):
    """[T, n_obs] the std of each step's disturbance (traced) at states obs [T, n_obs] and
    controls u [T, n_act]; mis = `Mismatch.arrays()`."""
    coef, rest, speed, mid, half = mis
    var = _mismatch_features(obs, u, nq, rest, speed, mid, half) @ coef.T
    # the floor keeps the square root's derivative finite where the model has no mismatch
    return jnp.sqrt(jnp.maximum(var, 0.0) + 1e-30)


def _penalty(obs, lim):
    """Sum of the squared excesses over the joints' and speed limits, in units of the limit
    (traced): the optimisers' soft constraint, checked exactly afterwards."""
    _, _, q_low, q_high, speed = lim
    nq = q_low.shape[0]
    q, qd = obs[..., :nq], obs[..., nq:]
    span_q = jnp.where(jnp.isfinite(q_high - q_low), q_high - q_low, 1.0)
    over_q = jnp.where(jnp.isfinite(q_high), jax.nn.relu(q - q_high), 0.0) + jnp.where(
        jnp.isfinite(q_low), jax.nn.relu(q_low - q), 0.0
    )
    over_v = jnp.where(jnp.isfinite(speed), jax.nn.relu(jnp.abs(qd) - speed), 0.0)
    span_v = jnp.where(jnp.isfinite(speed), speed, 1.0)
    return jnp.sum((over_q / span_q) ** 2) + jnp.sum((over_v / span_v) ** 2)


def _records(obs, u) -> tuple[np.ndarray, np.ndarray]:
    """Records' observations [E, T+1, n_obs] and controls [E, T, n_act] as float64, refused
    (ValueError) where their shapes do not match."""
    obs, u = np.asarray(obs, np.float64), np.asarray(u, np.float64)
    if obs.ndim != 3 or u.shape[:2] != (obs.shape[0], obs.shape[1] - 1):
        raise ValueError(
            f"obs {obs.shape} and u {u.shape} do not match: give the records' observations "
            "[E, T+1, n_obs] and the controls applied between them [E, T, n_act]"
        )
    return obs, u


def _f32(*xs):
    return tuple(jnp.asarray(x, jnp.float32) for x in xs)


def _pick(criterion, labels: list[str]):
    """None for D; the weights over the parameters' relative variances otherwise. A dict
    {parameter: relative half-width asked} weighs each by 1 / asked^2: the sum of
    (relative variance / asked^2) is dominated by the parameter furthest from its width, so
    the design spends the record on what is asked (a weighted A-, for one parameter a
    c-optimal design), not on the determinant over every candidate's parameters."""
    if isinstance(criterion, dict):
        unknown = sorted(set(criterion) - set(labels))
        bad = {k: v for k, v in criterion.items() if not float(v) > 0}
        if unknown or bad or not criterion:
            raise ValueError(
                f"criterion {criterion!r}: give {{parameter: relative half-width > 0}} over "
                f"fitted parameters of {labels}"
            )
        return np.array([1.0 / float(criterion[k]) ** 2 if k in criterion else 0.0 for k in labels])
    if criterion == "D":
        return None
    if criterion == "A":
        return np.ones(len(labels))
    if criterion in labels:
        return (np.array(labels) == criterion).astype(np.float64)
    raise ValueError(
        f"criterion {criterion!r} is unknown: choose 'D' (determinant), 'A' (trace), one "
        f"fitted parameter of {labels} or {{parameter: relative half-width asked}}"
    )


def lqr_gain(designer: Designer, estimate: dict | None, x_ref, u_ref=None, q=None, r=None):
    """[n_act, n_obs] the discrete LQR gain of the simulator linearised at (x_ref, u_ref) (an
    equilibrium: pole down or up), at the estimate with the fitted candidates' parameters
    (smooth laws only: a friction's tanh at rest is not linearised, it is left off). Weights
    q [n_obs] (default 1) and r [n_act] (default 1 per squared half range)."""
    sim = designer.sim
    theta = designer.theta(estimate)
    theta[designer.slots] = np.asarray(designer.model.nominal)[designer.slots]
    params = designer.model.params(jnp.asarray(theta, jnp.float32))
    x_ref = jnp.asarray(x_ref, jnp.float32)
    u_ref = jnp.zeros(sim.n_act, jnp.float32) if u_ref is None else jnp.asarray(u_ref, jnp.float32)

    def f(x, u):
        state = sim.init(x[: sim.nq], x[sim.nq :], params)
        return sim.observe(params, sim.step(params, state, u))

    a = np.asarray(jax.jacfwd(f, argnums=0)(x_ref, u_ref), np.float64)
    b = np.asarray(jax.jacfwd(f, argnums=1)(x_ref, u_ref), np.float64)
    half = 0.5 * np.ptp(np.asarray(sim.ctrl_range, np.float64), axis=1)
    qm = np.diag(np.ones(sim.n_obs) if q is None else np.asarray(q, np.float64))
    rm = np.diag(1.0 / half**2 if r is None else np.asarray(r, np.float64))
    p = scipy.linalg.solve_discrete_are(a, b, qm, rm)
    return np.linalg.solve(rm + b.T @ p @ b, b.T @ p @ a)


# -- fitting a record, as discovery's fit does, with one compiled program ------------------


class WindowFit:
    """Discovery's fit (`Engine.fit`, measured initial states) of the designer's parameters on
    up to `max_episodes` episodes of `steps` steps: the arrays are padded to that many, so one
    program serves every amount of data. Returns estimates and 95% half-widths
    (`confidence_intervals`: noise part and law-mismatch part)."""

    def __init__(self, designer: Designer, max_episodes: int, iterations: int = 30):
        self.d, self.max_episodes, self.iterations = designer, int(max_episodes), iterations

    def data(self, obs: np.ndarray, acts: np.ndarray):
        e, t1, n_obs = obs.shape
        if e > self.max_episodes or t1 != self.d.steps + 1:
            raise ValueError(
                f"{e} episodes of {t1 - 1} steps: this fit takes at most {self.max_episodes} "
                f"of {self.d.steps}"
            )
        pad = self.max_episodes - e
        obs_p = np.concatenate([obs, np.zeros((pad, t1, n_obs))])
        acts_p = np.concatenate([acts, np.zeros((pad, t1 - 1, acts.shape[-1]))])
        starts = self.d.starts
        episode = np.repeat(np.arange(self.max_episodes), len(starts)).astype(np.int32)
        start = np.tile(starts, self.max_episodes).astype(np.int32)
        mask = (episode < e).astype(np.float32)
        flat = obs.reshape(-1, n_obs)
        std = flat.std(axis=0)
        scale = np.maximum(std, 1e-6 * std.max() + 1e-12)
        return tuple(
            jnp.asarray(x, dt)
            for x, dt in (
                (obs_p, jnp.float32),
                (acts_p, jnp.float32),
                (episode, jnp.int32),
                (start, jnp.int32),
                (mask, jnp.float32),
                (scale, jnp.float32),
            )
        ), scale

    def __call__(self, obs, acts, theta0, noise=None) -> dict:
        """The fit from theta0; `noise` [n_obs] the sensor noise std, None: measured from the
        fit's own one-step residuals (`Designer.sensor_noise`), returned as "noise"."""
        from hds.discover.fit import confidence_intervals

        d = self.d
        obs, acts = np.asarray(obs, np.float64), np.asarray(acts, np.float64)
        data, scale = self.data(obs, acts)
        slots = d.slots[None, :]
        delay = np.zeros((1, d.sim.n_act), np.int32)
        theta, loss, h, g, _, vh, vg = d.engine.fit(
            np.asarray(theta0, np.float64)[None], slots, delay, data, self.iterations
        )
        # what the noise alone leaves, the initial states' noise propagated included; and the
        # floor's own uncertainty: a variance from n residuals' median absolute deviation has
        # a relative standard error of 2.33 / sqrt(n), and a misfit within FLOOR_Z of them
        # is not counted as law mismatch (the misfit is the loss above the floor times every
        # entry: a floor a few percent low would read as a mismatch)
        if noise is None:
            noise, used = d._sensor_noise(theta[0], obs, acts)
            spread = FLOOR_Z * 2.33 / math.sqrt(max(used, 1))
        else:
            spread = 0.0
        floor2 = d.noise_loss(theta[0], obs, acts, noise, scale) * (1.0 + spread)
        count = float(len(obs) * len(d.starts) * d.horizon * d.sim.n_obs)
        misfit = max(float(loss[0]) - floor2, 0.0) * count
        values = np.asarray(theta[0], np.float64)[d.slots]
        full = confidence_intervals(values, h[0], g[0], misfit, (vh[0], vg[0]))
        return {
            "values": values,
            "half": full.half,  # noise and law mismatch: what discovery reports
            "noise_half": full.half - full.bias,  # the noise part alone
            "theta": np.asarray(theta[0], np.float64),
            "noise": np.asarray(noise, np.float64),
            # the residuals' level over the sensor noise's (1: the model fits to the noise;
            # above: law mismatch the noise part of the next prediction does not hold)
            "residual_over_noise": math.sqrt(max(float(loss[0]), 0.0) / max(floor2, 1e-30)),
        }


def split_estimate(env_cfg, names) -> tuple[object, dict]:
    """(env_cfg without its effects of the kinds `names`, those effects' parameters as an
    estimate {"<effect>@<target>": {param: value}}): a corrected simulator's found effects
    become the traced estimate of a design on the uncorrected one. Action delays (shifts,
    nothing to design for) stay on the simulator."""
    from hds.discover.workflow import replace_env
    from hds.effects.apply import as_spec
    from hds.effects.library import effect_type

    specs = [as_spec(e) for e in env_cfg.effects]
    found = [
        i for i, e in enumerate(specs) if e.name in names and not effect_type(e.name).shifts_actions
    ]
    if not found:
        return env_cfg, {}
    estimate = {f"{specs[i].name}@{specs[i].target}": dict(specs[i].params) for i in found}
    kept = [e for i, e in enumerate(env_cfg.effects) if i not in found]
    return replace_env(env_cfg, effects=kept), estimate


def designed_controls(
    env_cfg, discover_cfg, dt: float, steps: int, episodes: int, scale, x0s, data=None
):
    """[E, T, n_act] open-loop excitation for a round of the loop (discover.excitation =
    designed): designed on `env_cfg`, the simulator corrected so far, for every candidate of
    discover.design_effects on its places, from the initial states x0s [S, n_obs] the episodes
    start from, within `scale` of the actuators' half range; the noise measured on `data` (a
    Dataset recorded on the plant), else assumed.

    The corrected simulator's own effects of those kinds are its current estimates: they are
    taken off the simulator and given to the design as the estimate (traced), so every round
    designs on one simulator, and one Designer (`get_designer`) serves them all, refining the
    effects found so far as well as looking for the others."""
    from hds.discover.workflow import fit_backend, with_backend

    env_cfg = with_backend(env_cfg, fit_backend(env_cfg, discover_cfg.backend))
    names = list(discover_cfg.design_effects)
    env_cfg, estimate = split_estimate(env_cfg, names)
    probe = get_engine(env_cfg, dt, names, 0, 0, discover_cfg.horizon).model
    keys = [c.key for c in probe.candidates if not c.shifts_actions]
    if not keys:
        raise ValueError(
            f"discover.design_effects = {names} has no effect with a parameter to design for "
            "on this system (an action delay is an integer shift, not a parameter the "
            "information is taken of): add e.g. coulomb_friction or actuator_gain"
        )
    designer = get_designer(env_cfg, keys, dt, steps, discover_cfg.horizon, discover_cfg.stride)
    noise = None
    if data is not None:  # the model's one-step residuals on the plant's record, at the estimate
        noise = designer.sensor_noise(designer.theta(estimate), data.obs, data.actions)
    limits = limits_of(env_cfg, float(scale))
    design = designer.design(estimate, x0s, noise, limits, seed=discover_cfg.seed)
    return np.repeat(design.controls()[None], episodes, axis=0)


def excitation_controls(
    discover_cfg, env_cfg, dt: float, steps: int, q0, qd0, scale: float, random_steps, data=None
) -> np.ndarray:
    """The open-loop controls [E, steps, n_act] of excitation episodes recorded on the plant
    from the initial states (q0 [E, nq], qd0 [E, nv]), as every caller records them (the loop's
    rounds, the corrected simulator): with discover.excitation = designed, designed on `env_cfg`
    (the simulator corrected so far: its effects hold the current estimates) within `scale` of
    the actuators' half range (`designed_controls`, the expected information over the first
    few initial states, the noise measured on `data`); otherwise, and where no design keeps
    the limits (a warning says why), `random_steps()`: the fallback, random steps whose
    amplitude `record_until_identifiable` doubles while the data cannot identify a candidate."""
    if discover_cfg.excitation == "designed":
        x0s = np.concatenate([q0, qd0], axis=1)[:4]  # the expected information over these
        try:
            return designed_controls(env_cfg, discover_cfg, dt, steps, len(q0), scale, x0s, data)
        except ValueError as err:  # no design keeps the limits: random steps, as before
            log.warning("designed excitation failed (%s); random steps instead", err)
    return random_steps()
