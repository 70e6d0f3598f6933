"""hds.discover.design: the fit's sensitivities through the simulator, the limits a design keeps,
and a designed record identifying friction better than random steps of the same bounds."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from hds.data import collect
from hds.data.excitation import random_steps
from hds.discover.design import (
    Designer,
    Mismatch,
    MismatchMean,
    WindowFit,
    get_designer,
    half_width,
    limits_of,
    lqr_gain,
    split_estimate,
    typical_scale,
    with_mismatch,
)

FRICTION = "coulomb_friction@slider"


class CompileCount:
    """XLA compiles (or persistent-cache loads) of programs while open (jax.monitoring)."""

    EVENT = "/jax/core/compile/backend_compile_duration"

    def __enter__(self):
        import jax

        self.n = 0
        jax.monitoring.register_event_duration_secs_listener(self._record)
        return self

    def _record(self, event, secs, **_):
        self.n += event == self.EVENT

    def __exit__(self, *exc):
        import jax

        jax.monitoring.unregister_event_duration_listener(self._record)


DOWN = np.array([0.0, np.pi, 0.0, 0.0])  # cart centred, pole hanging, at rest


def fourier(designer, coef):
    """[T, n_act] a tanh Fourier series of the designer's harmonics (in [-1, 1])."""
    t = np.arange(designer.steps) * designer.dt
    phase = 2 * np.pi * t[:, None] * designer.frequencies[None, :]
    return np.tanh(np.concatenate([np.sin(phase), np.cos(phase)], axis=1) @ coef.T)


@pytest.fixture(scope="module")
def analytic_cfg(cartpole_cfg):
    return dataclasses.replace(cartpole_cfg, backend="analytic", effects=[])


@pytest.fixture(scope="module")
def small(analytic_cfg):
    """Friction and gain on the cart, 16-step episodes, 3-step windows every 2 steps."""
    return Designer(
        analytic_cfg, [FRICTION, "actuator_gain@slide"], 0.04, 16, horizon=3, stride=2, harmonics=3
    )


@pytest.fixture(scope="module")
def residuals(small):
    """The windows' residuals, compiled once for the module's tests (eager, each call traces
    the windows' scans again)."""
    import jax

    return jax.jit(small.residuals)


def test_information_matches_finite_differences(small, residuals):
    """J^T Sigma^-1 J of the windows, J forward mode through the simulator, against central
    differences of the same residuals (float32: a step of 1% of each parameter)."""
    theta = small.theta({FRICTION: {"force": 30.0}, "actuator_gain@slide": {"gain": 0.9}})
    rng = np.random.default_rng(0)
    u = rng.uniform(-2.0, 2.0, (small.steps, 1))
    obs = [DOWN]
    sim, params = small.sim, small.model.params(jnp.asarray(theta, jnp.float32))
    state = sim.init(jnp.asarray(DOWN[:2]), jnp.asarray(DOWN[2:]), params)
    for t in range(small.steps):
        state = sim.step(params, state, jnp.asarray(u[t], jnp.float32))
        obs.append(np.asarray(sim.observe(params, state)))
    obs = np.asarray(obs)
    obs = obs + rng.normal(0, 0.01, obs.shape)  # a record the model does not fit exactly
    noise = np.array([1e-3, 2e-3, 1e-2, 2e-2])
    info = small.information(theta, obs, u, noise)

    def res(th):
        r = residuals(
            jnp.asarray(th, jnp.float32),
            jnp.asarray(obs, jnp.float32),
            jnp.asarray(u, jnp.float32),
            jnp.asarray(1.0 / noise, jnp.float32),
        )
        return np.asarray(r, np.float64)

    cols = []
    for s in small.slots:
        h = 0.01 * abs(theta[s])
        up, down = theta.copy(), theta.copy()
        up[s] += h
        down[s] -= h
        cols.append((res(up) - res(down)) / (2 * h))
    j = np.stack(cols, axis=1)
    expected = j.T @ j
    assert np.all(np.diag(info) > 0)
    np.testing.assert_allclose(info, expected, rtol=0.03, atol=1e-3 * np.abs(expected).max())


def test_noise_pull_matches_central_differences(small, analytic_cfg, residuals):
    """The estimator's noise pull B (closed form: J^T dr/dn through the windows' initial states
    and targets) against central differences of the fit's gradient J^T r in the noise, on the
    model's own trajectory (where the fit's linearisation is taken)."""
    import jax

    theta = jnp.asarray(
        small.theta({FRICTION: {"force": 30.0}, "actuator_gain@slide": {"gain": 0.9}}), jnp.float32
    )
    limits = limits_of(analytic_cfg, 0.5)
    coef = np.random.default_rng(1).normal(0.0, 0.6, (1, 6))
    ff = 1.5 * fourier(small, coef)
    args = (theta, ff, np.zeros((1, 4)), DOWN, DOWN, limits.u_low, limits.u_high)
    obs, u = small._rollout(*(jnp.asarray(a, jnp.float32) for a in args))
    noise = jnp.asarray([1e-3, 2e-3, 1e-2, 2e-2], jnp.float32)
    scale = jnp.asarray(np.asarray(obs).std(axis=0), jnp.float32)
    h, b = jax.jit(small._sandwich_fn)(theta, obs, u, noise, scale)
    b = np.asarray(b, np.float64)

    weight = 1.0 / scale

    def pull(n):  # the fit's gradient on the record with noise n (in units of its std)
        noisy = obs + jnp.asarray(n, jnp.float32) * noise
        j = np.asarray(small._jac(theta, noisy, u, weight), np.float64)
        return j.T @ np.asarray(residuals(theta, noisy, u, weight), np.float64)

    # small steps along random directions: the friction's tanh at rest is resolved within
    # the noise (1 cm/s against 1 / sharpness = 2 cm/s), so a step of one std is not linear
    eps = 0.05
    for n in np.random.default_rng(2).normal(size=(3, *obs.shape)):
        expected = (pull(eps * n) - pull(-eps * n)) / (2 * eps)
        np.testing.assert_allclose(b @ n.reshape(-1), expected, rtol=0.02, atol=1e-6)
    j = np.asarray(small._jac(theta, obs, u, weight), np.float64)
    np.testing.assert_allclose(np.asarray(h), j.T @ j, rtol=1e-4)


def test_sensor_noise_from_the_model_residuals(small, analytic_cfg, residuals):
    """Records of a bang-bang-like drive with friction (the simulator's own laws) plus white
    noise of a known std: the noise from the model's one-step residuals at the true
    parameters is the known one on every channel, at two noise levels, while the motion
    alone (no noise) shows none; and the fit's residual floor under that noise is the mean
    squared residual of its windows."""
    theta = small.theta({FRICTION: {"force": 30.0}, "actuator_gain@slide": {"gain": 0.9}})
    limits = limits_of(analytic_cfg, 1.0)
    rng = np.random.default_rng(3)
    clean, controls = [], []
    for _ in range(96):  # saturating Fourier drives: the cart reverses within a few steps
        coef = rng.normal(0.0, 3.0, (1, 6))
        bounds = (limits.u_low, limits.u_high)
        args = (theta, 3.0 * fourier(small, coef), np.zeros((1, 4)), DOWN, DOWN, *bounds)
        obs, u = small._rollout(*(jnp.asarray(a, jnp.float32) for a in args))
        clean.append(np.asarray(obs, np.float64))
        controls.append(np.asarray(u, np.float64))
    clean, controls = np.stack(clean), np.stack(controls)
    sigma = np.array([1e-3, 2e-3, 1e-2, 2e-2])
    for level in (1.0, 0.2):
        noisy = clean + rng.normal(size=clean.shape) * sigma * level
        estimate = small.sensor_noise(theta, noisy, controls)
        np.testing.assert_allclose(estimate / (sigma * level), 1.0, atol=0.15)
    assert np.all(small.sensor_noise(theta, clean, controls) < 0.05 * sigma)
    # the fit's residual floor under that noise: the windows' measured initial states carry
    # noise too, so the mean squared normalized residual is above the targets' noise alone
    # (the last, smaller noise level: the windows' residuals are linear in it)
    scale = clean.reshape(-1, 4).std(axis=0)
    floor = small.noise_loss(theta, noisy, controls, sigma * level, scale)
    theta32, weight = jnp.asarray(theta, jnp.float32), jnp.asarray(1.0 / scale, jnp.float32)
    r = np.concatenate(
        [
            residuals(theta32, jnp.asarray(o), jnp.asarray(u), weight)
            for o, u in zip(noisy, controls)
        ]
    )
    targets_only = np.mean((sigma * level / scale) ** 2)
    assert floor > 1.2 * targets_only
    assert np.mean(np.asarray(r, np.float64) ** 2) == pytest.approx(floor, rel=0.1)
    with pytest.raises(ValueError, match="obs"):
        small.sensor_noise(theta, clean, controls[:, :-1])


@pytest.fixture(scope="module")
def disturbed(small):
    """Records of the model driven by controls u [T, n_act] from x0 with a disturbance added
    to every step's state (x_(t+1) = f(x_t, u_t) + d_t: a law mismatch), d_t = z_t x (base_t
    + bump exp(-(v_t / width)^2)), v_t the cart's velocity at x_t: z [T, n_obs] vmapped over
    draws; compiled once for the module."""
    import jax

    empty = jnp.zeros((0, 1), jnp.float32)

    def one(theta, x0, u, z, base, bump, width):
        params = small.model.params(theta)

        def step(x, xs):
            ut, zt, bt = xs
            std = bt + bump * jnp.exp(-((x[2] / width) ** 2))
            x1 = small.model.window(params, x, empty, ut[None])[0] + zt * std
            return x1, x1

        return jnp.concatenate([x0[None], jax.lax.scan(step, x0, (u, z, base))[1]])

    vmapped = jax.jit(jax.vmap(one, in_axes=(None, None, None, 0, None, None, None)))

    def run(theta, x0, u, z, base, bump=(0.0, 0.0, 0.0, 0.0), width=1.0):
        return vmapped(theta, x0, u, *(jnp.asarray(a, jnp.float32) for a in (z, base, bump, width)))

    return run


def _drive(small, analytic_cfg, theta, seed, gain=1.5):
    """A smooth drive's trajectory [T+1, n_obs] and controls [T, n_act] on the model."""
    limits = limits_of(analytic_cfg, 0.5)
    coef = np.random.default_rng(seed).normal(0.0, 0.6, (1, 6))
    args = (theta, gain * fourier(small, coef), np.zeros((1, 4)), DOWN, DOWN)
    obs, u = small._rollout(
        *(jnp.asarray(a, jnp.float32) for a in (*args, limits.u_low, limits.u_high))
    )
    return obs, u


def test_mismatch_pull_matches_the_disturbed_records(small, analytic_cfg, residuals, disturbed):
    """A law mismatch as a disturbance of each step: its columns of the estimator's pull B
    (adjoint through the one-step Jacobians) against central differences of the fit's gradient
    on records simulated with the disturbance; and, on a linearised (small-noise) case, the
    estimator's scatter over 400 records with sensor noise and the disturbance is the
    predicted H^-1 B B^T H^-1, wider than the sensor-noise prediction by the predicted amount."""
    import jax

    theta = jnp.asarray(
        small.theta({FRICTION: {"force": 30.0}, "actuator_gain@slide": {"gain": 0.9}}), jnp.float32
    )
    obs, u = _drive(small, analytic_cfg, theta, 1)
    noise = np.array([1e-3, 2e-3, 1e-2, 2e-2])
    scale = jnp.asarray(np.asarray(obs).std(axis=0), jnp.float32)
    # a disturbance of the velocities, largest near the cart's rest
    coef = np.zeros((4, 8))
    coef[2, 0], coef[3, 0], coef[2, 1] = 1.6e-4, 4e-4, 1.6e-3
    mismatch = Mismatch(coef, np.array([0.05, 0.5]), np.ones(2), np.zeros(1), np.ones(1))
    sandwich = jax.jit(small._sandwich_fn)
    h, b = sandwich(theta, obs, u, jnp.asarray(noise, jnp.float32), scale, small._mis(mismatch))
    h, b = np.asarray(h, np.float64), np.asarray(b, np.float64)
    n_sensor = obs.size
    bp = b[:, n_sensor:]
    std = np.sqrt(mismatch.variance(np.asarray(obs[:-1]), np.asarray(u)))  # [T, n_obs]
    weight = 1.0 / scale
    j0 = np.asarray(small._jac(theta, obs, u, weight), np.float64)

    def pull(d):
        rec = disturbed(theta, obs[0], u, d[None], np.ones_like(std))[0]
        j = np.asarray(small._jac(theta, rec, u, weight), np.float64)
        return j.T @ np.asarray(residuals(theta, rec, u, weight), np.float64)

    eps = 0.05
    for z in np.random.default_rng(4).normal(size=(3, *std.shape)):
        expected = (pull(eps * z * std) - pull(-eps * z * std)) / (2 * eps)
        np.testing.assert_allclose(bp @ z.reshape(-1), expected, rtol=0.03, atol=1e-6)

    # the linearised estimator's scatter: 1% of the sizes above keeps the windows linear
    small_noise, small_std = 0.01 * noise, 0.01 * std
    rng = np.random.default_rng(5)
    z = rng.normal(size=(400, *std.shape))
    n = rng.normal(size=(400, *obs.shape)) * small_noise
    recs = np.asarray(disturbed(theta, obs[0], u, z, small_std), np.float64) + n
    res_all = jax.vmap(residuals, in_axes=(None, 0, None, None))
    r = np.asarray(res_all(theta, jnp.asarray(recs, jnp.float32), u, weight), np.float64)
    shift = -(np.linalg.solve(h, j0.T @ r.T)).T  # one Gauss-Newton step from the truth
    # the predicted covariance at the same sizes: B's columns scale with the noise and std
    b_small = np.concatenate([b[:, :n_sensor], bp], axis=1) * 0.01
    inv = np.linalg.inv(h)
    with_mis = np.diag(inv @ b_small @ b_small.T @ inv)
    sensor_only = np.diag(inv @ b_small[:, :n_sensor] @ b_small[:, :n_sensor].T @ inv)
    np.testing.assert_allclose(shift.var(axis=0) / with_mis, 1.0, atol=0.2)
    assert np.all(with_mis > 2.0 * sensor_only)  # the mismatch widens the intervals
    # the public prediction of the same record holds it: the design's standard errors
    estimate = {FRICTION: {"force": 30.0}, "actuator_gain@slide": {"gain": 0.9}}
    se_mis = small.predicted_se_of(estimate, np.asarray(u)[None], DOWN, noise, mismatch)
    se_sensor = small.predicted_se_of(estimate, np.asarray(u)[None], DOWN, noise)
    np.testing.assert_allclose(se_mis**2, with_mis / 0.01**2, rtol=0.02)
    np.testing.assert_allclose(se_sensor**2, sensor_only / 0.01**2, rtol=0.02)


def test_mismatch_estimate_recovers_an_injected_disturbance(small, analytic_cfg, disturbed):
    """Records of the model under a known state-dependent disturbance of the cart's velocity
    (large near rest, none when sliding fast: a friction law that differs at reversals) and
    white sensor noise: the mismatch estimated from the one-step residuals (beside the sensor
    noise measured from them) has the injected variance at rest and at slow slides within
    30%, and next to none where none was injected."""
    theta = jnp.asarray(
        small.theta({FRICTION: {"force": 30.0}, "actuator_gain@slide": {"gain": 0.9}}), jnp.float32
    )
    noise = np.array([1e-3, 2e-3, 1e-2, 2e-2])
    rng = np.random.default_rng(6)
    recs, controls, true_var = [], [], []
    # 3 cm/s at rest, fading over 0.15 m/s (a disturbance alike on every step would be, by
    # its variance, the velocity's sensor noise: `Designer.mismatch`)
    base = np.zeros((small.steps, 4))
    bump = np.array([0.0, 0.0, 0.03, 0.0])
    for e in range(64):
        obs, u = _drive(small, analytic_cfg, theta, 100 + e, gain=3.0)
        z = rng.normal(size=(1, small.steps, 4))
        rec = np.asarray(disturbed(theta, obs[0], u, z, base, bump, 0.15)[0], np.float64)
        v_rec = rec[:-1, 2]  # the injected std at the record's states
        true_var.append((0.03 * np.exp(-((v_rec / 0.15) ** 2))) ** 2)
        recs.append(rec + rng.normal(size=rec.shape) * noise)
        controls.append(np.asarray(u, np.float64))
    recs, controls, true_var = np.stack(recs), np.stack(controls), np.stack(true_var)
    sensor = small.sensor_noise(theta, recs, controls)
    mis = small.mismatch(theta, recs, controls, sensor)
    est = mis.variance(recs[:, :-1], controls)  # [E, T, n_obs]
    v = np.abs(recs[:, :-1, 2])
    np.testing.assert_allclose(sensor / noise, 1.0, atol=0.15)  # the noise is still the noise
    for region in (v < 0.05, (v >= 0.05) & (v < 0.2)):
        assert region.sum() > 30
        ratio = est[..., 2][region].mean() / true_var[region].mean()
        assert ratio == pytest.approx(1.0, abs=0.3), (region.sum(), ratio)
    # none while sliding fast, on either velocity (within a tenth of the rest's; at rest the
    # smoothed friction is not linear over the velocity's noise, which the residuals hold too)
    rest_var = true_var[v < 0.05].mean()
    assert est[..., 2][v > 0.5].mean() < 0.1 * rest_var
    assert est[..., 3][v > 0.5].mean() < 0.1 * rest_var


@pytest.fixture(scope="module")
def drifted(small):
    """Records [N, T+1, n_obs] of the model from x0 under open-loop controls u [T, n_act] with a
    law mismatch's mean added to every step, x_(t+1) = f(x_t, u_t) + bump exp(-(v_t / width)^2)
    (v_t the cart's velocity: a law that differs near rest), plus sensor noise n [N, T+1,
    n_obs]; and the records' windowed least-squares estimates (Gauss-Newton from theta, the
    windows weighted by `weight`): [N, M]. Compiled once for the module."""
    import jax

    empty = jnp.zeros((0, 1), jnp.float32)

    def one(theta, x0, u, bump, width, n):
        params = small.model.params(theta)

        def step(x, ut):
            x1 = small.model.window(params, x, empty, ut[None])[0]
            x1 = x1 + bump * jnp.exp(-((x[2] / width) ** 2))
            return x1, x1

        return jnp.concatenate([x0[None], jax.lax.scan(step, x0, u)[1]]) + n

    records = jax.jit(jax.vmap(one, in_axes=(None, None, None, None, None, 0)))
    residuals = jax.jit(small.residuals)

    def estimates(theta, x0, u, bump, width, n, weight, iterations=3):
        f32 = (jnp.asarray(a, jnp.float32) for a in (x0, u, bump, width, n, weight))
        x0, u, bump, width, n, weight = f32
        out = []
        for rec in records(theta, x0, u, bump, width, n):
            th = np.asarray(theta, np.float64)
            for _ in range(iterations):
                t32 = jnp.asarray(th, jnp.float32)
                j = np.asarray(small._jac(t32, rec, u, weight), np.float64)
                r = np.asarray(residuals(t32, rec, u, weight), np.float64)
                th[small.slots] -= np.linalg.lstsq(j, r, rcond=None)[0]
            out.append(th[small.slots])
        return np.array(out), np.asarray(records(theta, x0, u, bump, width, n), np.float64)

    return estimates


def _bump_mean(width, size, u_half):
    """A `MismatchMean` of size x exp(-(v / width)^2) on the cart's velocity alone."""
    coef = np.zeros((4, 16))
    coef[2, 13] = size  # the bump feature of the cart's velocity (`_mean_features`' order)
    return MismatchMean(
        coef,
        np.array([width, 1.0]),
        np.ones(2),
        np.ones(2),
        np.array([False, True]),
        np.zeros(1),
        np.atleast_1d(u_half),
    )


@pytest.mark.slow
def test_mismatch_mean_shift_matches_the_disturbed_fits(small, analytic_cfg, drifted):
    """A law mismatch's mean, a velocity disturbance near the cart's rest, on a linearised
    (small) case: the predicted shift of the estimate (`Designer.drag_of`: -H^-1 g along the
    model's trajectory) is the mean shift of the records' Gauss-Newton fits over 100 records
    with sensor noise, against the same records without the mismatch, within 30% (of the
    shift's size, the parameters relative to theirs), for three drives; and the mismatch's
    mean regressed from the one-step residuals (`Designer.mismatch_mean`) gives the
    disturbance back where the records go."""
    estimate = {FRICTION: {"force": 30.0}, "actuator_gain@slide": {"gain": 0.9}}
    theta = jnp.asarray(small.theta(estimate), jnp.float32)
    limits = limits_of(analytic_cfg, 0.5)
    noise = 0.01 * np.array([1e-3, 2e-3, 1e-2, 2e-2])
    width, size = 0.3, 1e-3
    mean = _bump_mean(width, size, limits.u_high)
    bump = np.array([0.0, 0.0, size, 0.0])
    n = np.random.default_rng(7).normal(size=(100, small.steps + 1, 4)) * noise
    for seed, gain in ((6, 1.5), (5, 1.5), (3, 0.5)):
        coef = np.random.default_rng(seed).normal(0.0, 0.6, (1, 6))
        u = limits.u_high * np.clip(gain * fourier(small, coef), -1.0, 1.0)
        predicted = small.drag_of(estimate, u[None], DOWN, noise, mean)
        std = small.open_loop(estimate, u, DOWN).std(axis=0)
        weight = 1.0 / np.maximum(std, 1e-6 * std.max())
        with_bump, _ = drifted(theta, DOWN, u, bump, width, n, weight)
        without, _ = drifted(theta, DOWN, u, 0 * bump, width, n, weight)
        # relative to each parameter's size; a component near nil (the gain's, on one drive)
        # is held to the shift's size, not its own
        ref = np.asarray(theta)[small.slots]
        shift = (with_bump - without).mean(axis=0) / ref
        error = np.linalg.norm(predicted["shift"] / ref - shift)
        assert error < 0.3 * np.linalg.norm(shift), (seed, predicted["shift"] / ref, shift)
        # the scatter the sandwich predicts for one signal is the sensor noise's alone
        np.testing.assert_allclose(predicted["se"], without.std(axis=0), rtol=0.3)
    # regressed from the one-step residuals at the truth, over several drives: the mean
    # disturbance on the cart's velocity within 25% of the bump where it matters, and on the
    # pole's (none injected) no more than noise; the bump as wide as the model's rest feature
    # (1 / sharpness + 3 noise: where a smoothed friction's law differs from a plant's)
    width = 1.0 / small.sim.sharpness + 3.0 * noise[2]
    recs, controls = [], []
    for seed in range(24):
        coef = np.random.default_rng(50 + seed).normal(0.0, 0.6, (1, 6))
        u = limits.u_high * np.clip(1.5 * fourier(small, coef), -1.0, 1.0)
        _, rec = drifted(theta, DOWN, u, bump, width, n[:1], np.ones(4))
        recs.append(rec[0])
        controls.append(u)
    recs, controls = np.stack(recs), np.stack(controls)
    est = small.mismatch_mean(theta, recs, controls, noise).mean(recs[:, :-1], controls)
    true = size * np.exp(-((recs[:, :-1, 2] / width) ** 2))
    assert np.abs(est[..., 2] - true).mean() < 0.25 * true.mean()
    # the pole's velocity had none: what stays is the regression's noise, the residuals'
    # noise (the pole's sensor noise and its initial state's, propagated) over sqrt(N / F)
    assert np.abs(est[..., 3]).mean() < 3.0 * noise[3] * np.sqrt(16 / true.size)


def _two_drives(small, analytic_cfg):
    """Two hand-made drives of one bound, an estimate, the sensor noise and a law mismatch's
    mean (a bump near the cart's rest) for the bias criterion's tests."""
    estimate = {FRICTION: {"force": 30.0}, "actuator_gain@slide": {"gain": 0.9}}
    limits = limits_of(analytic_cfg, 0.5)
    noise = 0.01 * np.array([1e-3, 2e-3, 1e-2, 2e-2])
    width, size = 0.3, 1e-3
    mean = _bump_mean(width, size, limits.u_high)
    signals = []
    for seed in (6, 5):
        coef = np.random.default_rng(seed).normal(0.0, 0.6, (1, 6))
        signals.append(limits.u_high * np.clip(1.5 * fourier(small, coef), -1.0, 1.0))
    return estimate, limits, noise, (width, size), mean, signals


def test_bias_criterion_turns_the_choice_of_two_drives(small, analytic_cfg):
    """The sensor-noise criterion prefers the first drive; with the mismatch's mean, the
    mean-squared-error criterion (the drag squared over 16 episodes beside the variance) the
    second; a mean of the wrong size is refused."""
    estimate, _, noise, _, mean, signals = _two_drives(small, analytic_cfg)
    sensor = [small.criterion_of(estimate, u, DOWN, noise, "A") for u in signals]
    mse = [
        small.criterion_of(estimate, u, DOWN, noise, "A", mismatch_mean=mean, episodes=16)
        for u in signals
    ]
    assert sensor[0] < sensor[1] and mse[1] < mse[0]
    with pytest.raises(ValueError, match="mismatch_mean has"):
        bad = dataclasses.replace(mean, coef=np.zeros((3, 16)))
        small.criterion_of(estimate, signals[0], DOWN, noise, mismatch_mean=bad)


@pytest.mark.slow  # 40 Gauss-Newton fits and two designs: about 20 s of CPU
def test_bias_criterion_picks_the_less_dragged_signal(small, analytic_cfg, drifted):
    """Of the two drives, the one the bias criterion picks is the one whose fits the mismatch
    drags less (the records' mean shift, measured as above)."""
    estimate, limits, noise, (width, size), mean, signals = _two_drives(small, analytic_cfg)
    theta = jnp.asarray(small.theta(estimate), jnp.float32)
    n = np.random.default_rng(8).normal(size=(40, small.steps + 1, 4)) * noise
    dragged = []
    for u in signals:
        std = small.open_loop(estimate, u, DOWN).std(axis=0)
        weight = 1.0 / np.maximum(std, 1e-6 * std.max())
        bump = np.array([0.0, 0.0, size, 0.0])
        with_bump, _ = drifted(theta, DOWN, u, bump, width, n, weight, iterations=2)
        without, _ = drifted(theta, DOWN, u, 0 * bump, width, n, weight, iterations=2)
        rel = (with_bump - without).mean(axis=0) / np.asarray(theta)[small.slots]
        dragged.append(float(np.sum(rel**2)))
    assert dragged[1] < 0.5 * dragged[0]  # the second, which the criterion picks
    # the design carries the drag it predicts; without a mean, none
    design = small.design(estimate, DOWN, noise, limits, iterations=2, mismatch_mean=mean)
    assert design.predicted_shift is not None and np.isfinite(design.predicted_shift).all()
    assert small.design(estimate, DOWN, noise, limits, iterations=2).predicted_shift is None
    with pytest.raises(ValueError, match="episodes"):
        small.design(estimate, DOWN, noise, limits, mismatch_mean=mean, episodes=0)


def test_one_designer_per_simulator_and_the_estimate_taken_off_it(analytic_cfg):
    """get_designer builds a Designer once per simulator, keys and record length; a corrected
    simulator's found friction becomes the design's estimate, its action delay stays on it."""
    first = get_designer(analytic_cfg, [FRICTION], 0.04, 16, horizon=3)
    assert get_designer(analytic_cfg, [FRICTION], 0.04, 16, horizon=3) is first
    assert get_designer(analytic_cfg, [FRICTION], 0.04, 20, horizon=3) is not first
    corrected = dataclasses.replace(
        analytic_cfg,
        effects=[
            {"name": "coulomb_friction", "target": "slider", "params": {"force": 42.0}},
            {"name": "action_delay", "target": "slide", "params": {"steps": 1}},
        ],
    )
    base, estimate = split_estimate(corrected, ["coulomb_friction", "action_delay"])
    assert estimate == {FRICTION: {"force": 42.0}}
    assert [e["name"] for e in base.effects] == ["action_delay"]
    assert get_designer(dataclasses.replace(base, effects=[]), [FRICTION], 0.04, 16, 3) is first
    assert first.theta(estimate)[first.slots[0]] == 42.0


@pytest.mark.slow  # compiles the design's nested derivatives: about a minute of CPU
def test_design_keeps_every_limit(small, analytic_cfg):
    """Half the control range, a speed bound the open-loop optimum would break and the rail's
    ends pulled in: the designed trajectory keeps them all; a design with an LQR feedback too."""
    limits = limits_of(analytic_cfg, amplitude=0.5, max_speed=[0.4, 20.0], joint_margin=0.49)
    assert limits.q_high[0] == pytest.approx(0.2) and limits.u_high[0] == pytest.approx(1.5)
    estimate = {FRICTION: {"force": 20.0}}
    for parameterisation in ("per_step", "fourier"):
        design = small.design(
            estimate, DOWN, None, limits, iterations=4, parameterisation=parameterisation
        )
        assert design.parameterisation == parameterisation
        obs, u = design.trajectory, design.planned_controls
        assert np.all(u <= limits.u_high + 1e-6) and np.all(u >= limits.u_low - 1e-6)
        assert np.all(np.abs(obs[:, 2:]) <= limits.max_speed + 1e-6)
        assert np.all(obs[:, :2] <= limits.q_high) and np.all(obs[:, :2] >= limits.q_low)
        assert np.all(np.isfinite(design.predicted_se)) and np.all(design.predicted_se > 0)
        assert design.limits.violation(obs, u) == {"control": 0.0, "joint": 0.0, "speed": 0.0}
        # the open-loop swing was shrunk for the speed bound: it is not the whole bound
        assert np.all(design.amplitude <= 0.5 * (limits.u_high - limits.u_low) + 1e-9)
        assert np.abs(design.unit_feedforward()).max() <= 1.0 + 1e-6

    gain = lqr_gain(small, estimate, DOWN)
    assert gain.shape == (1, 4) and np.all(np.isfinite(gain))
    # another estimate, feedback, noise and limits: traced inputs, nothing compiles again
    with CompileCount() as compiles:
        closed = small.design(
            {FRICTION: {"force": 35.0}}, DOWN, None, limits, iterations=2, gain=gain
        )
    assert compiles.n == 0
    assert closed.limits.violation(closed.trajectory, closed.planned_controls)["speed"] == 0.0
    # rivals: a signal beyond the bound is no fair rival; no control carries no information
    zero = np.zeros((small.steps, 1))
    over = np.full((small.steps, 1), 2 * limits.u_high[0])
    kept = small.design(
        estimate, DOWN, None, limits, iterations=2, rivals={"over": over, "zero": zero}
    )
    assert kept.signal == "designed"
    policy = closed.controller()
    u0 = policy(DOWN[None] + 0.1)
    assert u0.shape == (1, 1) and limits.u_low[0] <= u0[0, 0] <= limits.u_high[0]


def test_bad_input_fails_clearly(small, analytic_cfg):
    with pytest.raises(ValueError, match="criterion"):
        small.design(None, DOWN, None, limits_of(analytic_cfg), criterion="E")
    with pytest.raises(ValueError, match="relative half-width"):
        small.design(None, DOWN, None, limits_of(analytic_cfg), criterion={"gain": 0.03})
    with pytest.raises(ValueError, match="parameterisation 'spline' is unknown"):
        small.design(None, DOWN, None, limits_of(analytic_cfg), parameterisation="spline")
    with pytest.raises(ValueError, match="no candidate"):
        Designer(analytic_cfg, ["coulomb_friction@nowhere"], 0.04, 16, horizon=3)
    with pytest.raises(ValueError, match="amplitude"):
        limits_of(analytic_cfg, amplitude=0.0)


@pytest.mark.slow
def test_designed_record_narrower_than_random_steps(analytic_cfg):
    """A toy friction plant (the simulator's own law: no law mismatch, only sensor noise): a
    designed record of 4 episodes gives the fit a narrower interval on the friction than
    random steps of the same length and amplitude bound, and about the predicted one.

    With 4 episodes the fit's interval is a cluster-robust sandwich over 4 clusters: one noise
    draw's width scatters by about half of itself (here 0.05-0.12 for the design, 0.06-0.34
    for the steps), so one draw against one draw is a coin flip that a compiler flag's last
    digits can turn. Both records therefore meet the same 8 sensor-noise draws, and the test
    compares what the interval is on average (the median width) and what it is for (the
    estimates' scatter over the draws)."""
    from hds.envs import make_env
    from hds.real.brax_plant import BraxPlant

    steps, episodes, amplitude, force, draws = 50, 4, 0.5, 60.0, 8
    noise = np.array([1e-3, 2e-3, 1e-2, 2e-2])
    designer = Designer(analytic_cfg, [FRICTION], 0.04, steps, horizon=10, harmonics=6)
    fitter = WindowFit(designer, episodes)
    env = make_env(
        analytic_cfg,
        effects=[{"name": "coulomb_friction", "target": "slider", "params": {"force": force}}],
    )
    plant = BraxPlant(env)
    limits = limits_of(analytic_cfg, amplitude)
    design = designer.design({FRICTION: {"force": force}}, DOWN, noise, limits, iterations=40)
    q0, qd0 = np.tile(DOWN[:2], (episodes, 1)), np.zeros((episodes, 2))
    theta0 = designer.theta({FRICTION: {"force": 10.0}})
    ctrl = np.asarray(env.sim.ctrl_range, np.float64)

    def fits(u):
        """(widths, estimates) of the friction over the same noise draws for every record."""
        ds = collect(plant, env.task, q0, qd0, u)
        widths, values = [], []
        for draw in range(draws):
            obs = ds.obs + np.random.default_rng(draw).normal(size=ds.obs.shape) * noise
            fit = fitter(obs, ds.actions, theta0, noise=noise)
            assert abs(fit["values"][0] - force) < 0.05 * force
            widths.append(float(fit["noise_half"][0]))
            values.append(float(fit["values"][0]))
        return np.array(widths), np.array(values)

    designed, designed_values = fits(np.repeat(design.controls()[None], episodes, axis=0))
    steps_u = random_steps(0, episodes, steps, 0.04, ctrl, scale=amplitude)
    assert np.abs(steps_u).max() <= amplitude * 3.0 + 1e-9
    steps_widths, steps_values = fits(steps_u)
    assert np.median(designed) < np.median(steps_widths)
    # the narrower interval is a tighter estimate, not a smaller reported number
    assert designed_values.std() < steps_values.std()
    predicted = float(design.predicted_half(episodes)[0])
    assert 0.5 < predicted / np.median(designed) < 2.0


def test_per_step_bad_input_fails_clearly(small, analytic_cfg):
    limits = limits_of(analytic_cfg, 0.5)
    with pytest.raises(ValueError, match="x0 has shape"):
        small.per_step(None, DOWN[:2], np.ones(4), limits)
    with pytest.raises(ValueError, match="at least one start"):
        small.per_step(None, DOWN, np.ones(4), limits, restarts=0)
    with pytest.raises(ValueError, match="start 'prbs' has shape"):
        small.per_step(None, DOWN, np.ones(4), limits, starts={"prbs": np.zeros((3, 1))})


@pytest.mark.slow  # compiles the per-step criterion's gradient: about a minute of CPU
def test_per_step_keeps_every_limit_and_improves_on_its_start(small, analytic_cfg):
    """Every step's control free: the result keeps the amplitude bound, the rail pulled in
    and a speed bound on the model's trajectory, and carries more about the friction than the
    weak signal it started from."""
    limits = limits_of(analytic_cfg, amplitude=0.5, max_speed=[0.6, 20.0], joint_margin=0.45)
    estimate = {FRICTION: {"force": 20.0}, "actuator_gain@slide": {"gain": 1.0}}
    noise = np.array([1e-3, 2e-3, 1e-2, 2e-2])
    ctrl = np.array([[-3.0, 3.0]])
    weak = random_steps(0, 1, small.steps, 0.04, ctrl, scale=0.1)[0]
    criterion = {f"{FRICTION}.force": 0.05}
    best = small.per_step(
        estimate, DOWN, noise, limits, criterion, iterations=12, restarts=1, starts={"weak": weak}
    )
    u, obs = best["controls"], best["trajectory"]
    assert u.shape == (small.steps, 1)
    assert limits.violation(obs, u) == {"control": 0.0, "joint": 0.0, "speed": 0.0}
    assert best["value"] <= min(best["history"]) + 1e-9
    start_se = small.predicted_se_of(estimate, weak[None], DOWN, noise)
    assert best["predicted_se"][0] < start_se[0]


def test_with_mismatch_carries_the_fit_so_far():
    """The law mismatch measured on the fit so far, carried to the new record: nothing to
    carry before any data or without a mismatch; the scatter of the noise part scales the
    sensor prediction; the systematic part stays when every episode carries the same
    information (it does not average away). The fit so far's noise part is a typical draw of
    its 4 clusters (typical_scale(4) of the sensor part where the episodes scatter as the
    sensor noise alone)."""
    pred = np.array([0.02, 0.004])
    assert np.array_equal(with_mismatch(pred, 2, None, None, None, 0)[1], pred)
    sensor = np.array([0.05, 0.01])
    typical = sensor * typical_scale(4)
    # no mismatch: the noise part is the sensor part, the reported one the noise part
    noise_now, full_now = with_mismatch(pred, 8, sensor, typical, typical, 4)
    assert np.allclose(noise_now, pred) and np.allclose(full_now, pred)
    # episodes scatter twice the sensor noise: the noise part twice the prediction
    noise_now, _ = with_mismatch(pred, 8, sensor, 2 * typical, 2 * typical, 4)
    assert np.allclose(noise_now, 2 * pred)
    # the same signal for twice the episodes: se / sqrt(2), a bias of 0.3 stays 0.3
    from scipy import stats

    se4 = np.array([0.1, 0.02])
    sensor4 = stats.t.ppf(0.975, 3) * se4 / 2
    pred8 = half_width(se4, 8)
    noise4 = sensor4 * typical_scale(4)
    noise_now, full_now = with_mismatch(pred8, 8, sensor4, noise4, noise4 + 0.3, 4)
    assert np.allclose(full_now - noise_now, 0.3)
    with pytest.raises(ValueError, match="at least 2 episodes"):
        with_mismatch(pred, 8, pred, pred, pred, 1)


def test_typical_scale_is_the_median_of_the_fit_s_standard_error():
    """Episodes' gradients scattering with a known std, summing to zero at the fit: the noise
    part's standard error of `confidence_intervals` (a sandwich over the episodes as clusters)
    has its median at typical_scale(E) of the true one, well below it for few episodes."""
    from hds.discover.fit import confidence_intervals

    rng = np.random.default_rng(0)
    for episodes in (2, 4, 8):
        g = rng.normal(size=(4000, episodes, 1))
        g -= g.mean(axis=1, keepdims=True)  # the fit's optimum: the gradients sum to zero
        se = [confidence_intervals(np.ones(1), np.eye(1), ge).se[0] for ge in g]
        true = np.sqrt(episodes)  # the sum of E unit gradients' std, over a unit curvature
        assert np.median(se) / true == pytest.approx(typical_scale(episodes), rel=0.04)
    assert typical_scale(2) < 0.7 and typical_scale(16) > 0.97
    assert np.allclose(half_width([1.0], 16), 2.131 / 4 * typical_scale(16), rtol=1e-3)


def test_excitation_key_is_checked():
    from hds.config import DiscoverConfig

    assert DiscoverConfig().excitation == "steps"  # the old numbers stay the default
    with pytest.raises(ValueError, match="discover.excitation"):
        DiscoverConfig(excitation="chirp").check()
    with pytest.raises(ValueError, match="design_effects"):
        DiscoverConfig(design_effects=["no_such_effect"]).check()
    DiscoverConfig(excitation="designed").check()
