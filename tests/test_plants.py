"""The "real" plants: the brax plant (the simulator plus exact effects) and C MuJoCo.

Both agree with each other when no effect is set, and each effect of the library changes both
the way physics says, by the right amount. Most checks use the cart-pole's total horizontal
momentum p (cart + pole): only forces along the rail change it (the actuator, the slider's
damping, friction and limits; the hinge's forces are internal), so p(t) - p(0) plus the impulse
of the slider's own nominal damping, c0 * integral(xd dt), is the impulse of whatever an effect
adds. The pole hangs still (its stable equilibrium) unless a test says otherwise.
"""

from __future__ import annotations

import dataclasses

import jax
import mujoco
import numpy as np
import pytest
from conftest import make_config

from hds.effects import place
from hds.envs import make_env
from hds.envs.system import load_spec
from hds.real import make_plant
from hds.real.brax_plant import BraxPlant
from hds.real.mujoco_plant import MujocoPlant, mujoco_spec

KINDS = ("brax", "mujoco")


def hanging_angle(xml: str = "cartpole.xml") -> float:
    """The hinge angle at which the pole hangs still (pi for a vertical pole capsule; computed
    from the model, so a user MJCF with a tilted pole is handled too)."""
    x, _, z = load_spec(xml).compile().body("pole").ipos
    return float(np.pi - np.arctan2(x, z))


HANG = hanging_angle()
T = 13  # environment steps of 0.04 s: 0.52 s
B = 4  # episodes in every batch: one batch shape, so one compile per brax plant

# Effects whose nominal values make them exact no-ops (x * 1, x + 0, 0 * sign(v)). One brax
# plant carries them all, and a test sets their values by swapping `env.params`: one compile.
SWAPPABLE = {
    ("coulomb_friction", "slider"): {"force": 0.0},
    ("viscous_damping", "slider"): {"coefficient": 0.0},
    ("viscous_damping", "hinge"): {"coefficient": 0.0},
    ("actuator_gain", "slide"): {"gain": 1.0},
    ("actuator_offset", "slide"): {"offset": 0.0},
    ("actuator_deadzone", "slide"): {"width": 0.0},
    ("mass_scale", "cart"): {"scale": 1.0},
    ("mass_scale", "pole"): {"scale": 1.0},
    ("sensor_bias", "q_hinge"): {"bias": 0.0},
}


def effect(name, target, **params):
    return {"name": name, "target": target, "params": params}


class Plants:
    """Builds plants; brax plants are compiled once per static structure and then reused."""

    def __init__(self, env_cfg):
        self.env_cfg = env_cfg
        self.brax: dict[tuple, BraxPlant] = {}

    def __call__(self, kind: str, effects=(), friction_gap: float = 1.0):
        if kind == "mujoco":
            return MujocoPlant(self.env_cfg, effects, friction_gap)
        given = {(e["name"], e["target"]): e for e in effects}
        # action_delay (its length is static) and actuator_lag (its filter state) get a plant
        # of their own.
        extra = [e for k, e in given.items() if k not in SWAPPABLE]
        full = [given.get(k, effect(*k, **p)) for k, p in SWAPPABLE.items()] + extra
        key = tuple((e["name"], e["target"], e["params"].get("steps")) for e in extra)
        if key not in self.brax:
            self.brax[key] = BraxPlant(make_env(self.env_cfg, effects=full, sharpness=None))
        plant = self.brax[key]
        _, params = place(full, plant.env.sim.targets, friction_gap)
        plant.env = dataclasses.replace(plant.env, params=params)
        return plant


@pytest.fixture(scope="module")
def env_cfg():
    return make_config("real=mujoco").env


@pytest.fixture(scope="module")
def plants(env_cfg):
    return Plants(env_cfg)


@dataclasses.dataclass
class Run:
    obs: np.ndarray  # [B, T+1, n_obs]
    q: np.ndarray  # [B, T+1, nq], the true state
    qd: np.ndarray
    dt: float


def simulate(plants, kind, effects, q0, qd0, u, friction_gap=1.0) -> Run:
    """Build the plant and roll the open-loop controls u [B, T, n_act] out on it at once (a
    brax plant is shared: its effect values hold until the next `plants(...)` call)."""
    plant = plants(kind, effects, friction_gap)
    q0, qd0 = np.asarray(q0, float), np.asarray(qd0, float)
    obs, q, qd = [plant.reset(q0, qd0)], [q0], [qd0]
    for t in range(u.shape[1]):
        obs.append(plant.step(u[:, t]))
        state = plant.state()
        q.append(state[0])
        qd.append(state[1])
    return Run(*(np.stack(x, 1).astype(np.float64) for x in (obs, q, qd)), dt=plant.dt)


class Momentum:
    """Horizontal momentum of cart + pole from the state, with the nominal model's masses."""

    def __init__(self, env_cfg):
        self.model = load_spec(env_cfg.xml, env_cfg.timestep).compile()
        self.data = mujoco.MjData(self.model)
        self.cart = self.model.body("cart").id
        self.damping = float(self.model.dof_damping[self.model.joint("slider").dofadr[0]])
        self.gear = float(self.model.actuator_gear[0, 0])

    def __call__(self, q, qd):
        p = np.empty(q.shape[:-1])
        for i in np.ndindex(p.shape):
            self.data.qpos[:], self.data.qvel[:] = q[i], qd[i]
            mujoco.mj_forward(self.model, self.data)
            mujoco.mj_subtreeVel(self.model, self.data)
            p[i] = self.data.subtree_linvel[self.cart, 0] * self.model.body_subtreemass[self.cart]
        return p

    def impulse(self, run: Run, mass_scale: float = 1.0) -> np.ndarray:
        """[B, T+1]: the impulse of the rail forces other than the slider's nominal damping."""
        p = mass_scale * self(run.q, run.qd)
        xd = run.qd[..., 0]
        damping = self.damping * run.dt * np.cumsum(0.5 * (xd[:, 1:] + xd[:, :-1]), axis=1)
        return p - p[:, :1] + np.pad(damping, ((0, 0), (1, 0)))


@pytest.fixture(scope="module")
def momentum(env_cfg):
    return Momentum(env_cfg)


def at_rest():
    return np.tile([0.0, HANG], (B, 1)), np.zeros((B, 2))


def coasting():
    """Carts coasting at 1.5, 2.5, -2 and -1 m/s: the velocity keeps its sign over T."""
    q0, qd0 = at_rest()
    qd0[:, 0] = [1.5, 2.5, -2.0, -1.0]
    return q0, qd0, np.zeros((B, T, 1))


def constant(*u):
    return np.tile(np.reshape(u, (-1, 1, 1)), (1, T, 1))


def times(run: Run):
    return run.dt * np.arange(run.q.shape[1])


# Without effects -----------------------------------------------------------------------------


def test_brax_and_mujoco_agree_without_effects(plants):
    """0.52 s of random open-loop force (+-50 N) from states around the hanging pole. With an
    exact mass-matrix inverse in brax (matrix_inv_iterations 0 in the MJCF) the two engines
    agree to float32 precision: measured 2e-6 at most. Tolerance: 1e-4 on every variable."""
    rng = np.random.default_rng(0)
    q0 = np.array([0.0, HANG]) + rng.uniform(-0.2, 0.2, (B, 2))
    qd0 = rng.uniform(-0.3, 0.3, (B, 2))
    u = rng.uniform(-0.5, 0.5, (B, T, 1))
    brax, mj = (simulate(plants, k, [], q0, qd0, u) for k in KINDS)
    err = np.abs(brax.obs - mj.obs).max(axis=(0, 1))
    assert np.all(err < 1e-4), err
    assert np.abs(brax.obs - mj.obs).max() > 0  # two engines (float32, float64), not one twice


def test_brax_and_mujoco_agree_with_viscous_damping(plants):
    """Viscous damping is the joint's own damping in both plants, which MuJoCo's Euler and
    brax's (the cart-pole asks for an exact mass-matrix inverse) integrate implicitly: they
    agree as closely as without effects (measured: 2e-6 at most). An explicit force -c qd in
    brax, the law before, was 0.07 rad/s off in the pole's velocity, a tenth of what the
    damping changes."""
    rng = np.random.default_rng(1)
    q0 = np.array([0.0, HANG]) + rng.uniform(-1.0, 1.0, (B, 2))
    qd0 = rng.uniform(-3.0, 3.0, (B, 2))
    u = rng.uniform(-0.5, 0.5, (B, T, 1))
    damped = [effect("viscous_damping", "slider", coefficient=8.0)]
    damped += [effect("viscous_damping", "hinge", coefficient=0.6)]
    brax, mj = (simulate(plants, k, damped, q0, qd0, u) for k in KINDS)
    err = np.abs(brax.obs - mj.obs).max(axis=(0, 1))
    assert np.all(err < 1e-4), err


# Each effect, in both plants -------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_coulomb_friction_decelerates_at_the_friction_force(plants, momentum, kind):
    """Coasting carts: the momentum falls at exactly F (20 N) against the velocity's sign,
    compared with the same run without friction."""
    q0, qd0, u = coasting()
    force = 20.0
    rubbed = simulate(plants, kind, [effect("coulomb_friction", "slider", force=force)], q0, qd0, u)
    free = simulate(plants, kind, [], q0, qd0, u)
    lost = momentum.impulse(rubbed) - momentum.impulse(free)
    expected = -force * np.sign(qd0[:, :1]) * times(rubbed)
    assert np.abs(lost - expected).max() < 0.02 * force * times(rubbed)[-1]
    assert np.abs(momentum.impulse(free)).max() < 0.02  # no other rail force: N s


@pytest.mark.parametrize("kind", KINDS)
def test_viscous_damping_brakes_in_proportion_to_velocity(plants, momentum, kind):
    """The impulse lost is c * integral(xd dt), per cart: faster carts lose more."""
    q0, qd0, u = coasting()
    c = 8.0
    run = simulate(plants, kind, [effect("viscous_damping", "slider", coefficient=c)], q0, qd0, u)
    xd = run.qd[..., 0]
    distance = run.dt * np.sum(0.5 * (xd[:, 1:] + xd[:, :-1]), axis=1)
    lost = momentum.impulse(run)[:, -1]
    np.testing.assert_allclose(lost, -c * distance, rtol=0.03)
    assert abs(xd[1, -1]) < 0.92 * abs(qd0[1, 0])  # about exp(-c T / m), m = 15.5 kg


@pytest.mark.parametrize("kind", KINDS)
def test_actuator_gain_scales_the_force(plants, momentum, kind):
    q0, qd0 = at_rest()
    u = constant(0.3, -0.2, 0.5, -1.0)
    gain = 1.5
    run = simulate(plants, kind, [effect("actuator_gain", "slide", gain=gain)], q0, qd0, u)
    expected = gain * momentum.gear * u[:, 0] * times(run)  # N s
    np.testing.assert_allclose(momentum.impulse(run), expected, rtol=0.02, atol=0.05)


@pytest.mark.parametrize("kind", KINDS)
def test_actuator_offset_shifts_the_control_before_saturation(plants, momentum, kind):
    q0, qd0 = at_rest()
    u = constant(0.0, 0.3, -0.5, 2.9)
    offset = 0.2
    offsets = [effect("actuator_offset", "slide", offset=offset)]
    shifted = simulate(plants, kind, offsets, q0, qd0, u)
    reference = simulate(plants, kind, [], q0, qd0, np.clip(u + offset, -3, 3))
    np.testing.assert_allclose(shifted.obs, reference.obs, atol=1e-5)
    # zero control now pushes with the offset's force: 0.2 * 100 N
    np.testing.assert_allclose(momentum.impulse(shifted)[0], 20.0 * times(shifted), rtol=0.02)


@pytest.mark.parametrize("kind", KINDS)
def test_actuator_deadzone_removes_small_controls(plants, momentum, kind):
    q0, qd0 = at_rest()
    u = constant(0.15, -0.19, 0.5, -1.0)
    dead = simulate(plants, kind, [effect("actuator_deadzone", "slide", width=0.4)], q0, qd0, u)
    reference = simulate(plants, kind, [], q0, qd0, constant(0.0, 0.0, 0.3, -0.8))
    np.testing.assert_allclose(dead.obs, reference.obs, atol=1e-5)
    assert np.abs(dead.obs[:2] - dead.obs[:2, :1]).max() < 1e-6  # the small ones: no motion


@pytest.mark.parametrize("kind", KINDS)
def test_action_delay_shifts_the_response_by_whole_steps(plants, kind):
    """From rest the delayed plant holds still for N steps, then repeats the undelayed
    response exactly, N steps late."""
    rng = np.random.default_rng(2)
    q0, qd0 = at_rest()
    u = rng.uniform(-1.0, 1.0, (B, T, 1))
    n = 3
    late = simulate(plants, kind, [effect("action_delay", "slide", steps=n)], q0, qd0, u)
    now = simulate(plants, kind, [], q0, qd0, u)
    np.testing.assert_allclose(late.obs[:, : n + 1], now.obs[:, :1].repeat(n + 1, 1), atol=1e-6)
    np.testing.assert_allclose(late.obs[:, n:], now.obs[:, : T + 1 - n], atol=1e-5)


@pytest.mark.parametrize("kind", KINDS)
def test_actuator_lag_rises_with_its_time_constant(plants, momentum, env_cfg, kind):
    """A step of 50 N through a first-order lag of 0.1 s: at physics substep k the applied
    force is 50 (1 - a^(k+1)), a = exp(-h/tau); its impulse follows that exactly."""
    q0, qd0 = at_rest()
    u = constant(0.5, -0.5, 0.25, 1.0)
    tau, h = 0.1, env_cfg.timestep
    run = simulate(plants, kind, [effect("actuator_lag", "slide", time_constant=tau)], q0, qd0, u)
    a = np.exp(-h / tau)
    n = env_cfg.frames_per_step * np.arange(T + 1)  # physics substeps
    applied = h * (n - a * (1 - a**n) / (1 - a))  # h * sum_{k<n} (1 - a^(k+1))
    expected = momentum.gear * u[:, :1, 0] * applied
    impulse = momentum.impulse(run)
    np.testing.assert_allclose(impulse, expected, rtol=0.0, atol=0.02 * 50 * times(run)[-1])
    # at t = tau the lagged force has given much less than the instant one: (1 - ...) gap
    assert abs(impulse[0, 3]) < 0.7 * 50 * times(run)[3]


def heavy_and_light(plants, kind):
    """Cart and pole twice as heavy, and nominal, under the same forces (50 N, -30 N)."""
    q0, qd0 = at_rest()
    u = constant(0.5, -0.3, 0.2, -0.1)
    heavy_effects = [effect("mass_scale", b, scale=2.0) for b in ("cart", "pole")]
    return (
        u,
        simulate(plants, kind, heavy_effects, q0, qd0, u),
        simulate(plants, kind, [], q0, qd0, u),
    )


@pytest.mark.parametrize("kind", KINDS)
def test_mass_scale_divides_the_acceleration(plants, momentum, kind):
    """The same force gives the same momentum (of the doubled masses) at half the velocity."""
    u, heavy, light = heavy_and_light(plants, kind)
    force = momentum.gear * u[:, :1, 0]
    impulse = momentum.impulse(heavy, mass_scale=2.0)
    np.testing.assert_allclose(
        impulse[:, 1:] - impulse[:, 1:2], force * times(heavy)[:-1], rtol=0.02, atol=0.05
    )
    gained = [run.qd[:, -1, 0] - run.qd[:, 1, 0] for run in (heavy, light)]
    np.testing.assert_allclose(gained[0] / gained[1], 0.5, rtol=0.03)


@pytest.mark.parametrize("kind", KINDS)
def test_mass_scale_acts_from_the_first_step(plants, momentum, kind):
    u, heavy, _ = heavy_and_light(plants, kind)
    first = momentum.impulse(heavy, mass_scale=2.0)[:, 1]
    np.testing.assert_allclose(first, momentum.gear * u[:, 0, 0] * heavy.dt, rtol=0.05)


@pytest.mark.parametrize("kind", KINDS)
def test_sensor_bias_shifts_the_observation_only(plants, kind):
    rng = np.random.default_rng(3)
    q0, qd0 = at_rest()
    u = rng.uniform(-0.5, 0.5, (B, T, 1))
    biased = simulate(plants, kind, [effect("sensor_bias", "q_hinge", bias=0.1)], q0, qd0, u)
    clean = simulate(plants, kind, [], q0, qd0, u)
    np.testing.assert_allclose(
        biased.obs - clean.obs, np.broadcast_to([0, 0.1, 0, 0], clean.obs.shape), atol=1e-6
    )
    np.testing.assert_array_equal(biased.q, clean.q)
    np.testing.assert_array_equal(biased.qd, clean.qd)


@pytest.mark.parametrize("kind", KINDS)
def test_friction_gap_scales_friction(plants, momentum, kind):
    q0, qd0, u = coasting()
    rubbing = [effect("coulomb_friction", "slider", force=20.0)]
    half = simulate(plants, kind, rubbing, q0, qd0, u, friction_gap=0.5)
    free = simulate(plants, kind, [], q0, qd0, u)
    lost = momentum.impulse(half) - momentum.impulse(free)
    expected = -10.0 * np.sign(qd0[:, :1]) * times(half)
    assert np.abs(lost - expected).max() < 0.02 * 10.0 * times(half)[-1]
    none = simulate(plants, kind, rubbing, q0, qd0, u, friction_gap=0.0)
    np.testing.assert_allclose(none.obs, free.obs, atol=1e-6)


# Configuration and errors ----------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_a_bad_target_names_the_allowed_ones(kind):
    """Refused at validation, and by the plant's builder itself (its callers need not validate)."""
    allowed = r"no joint 'nope'.*\['slider', 'hinge'\]"
    bad = "real.effects=[{name: coulomb_friction, target: nope, params: {force: 1.0}}]"
    with pytest.raises(ValueError, match=rf"real.effects: .*{allowed}"):
        make_config(f"real.plant={kind}", bad)
    cfg = make_config(f"real.plant={kind}")
    real = dataclasses.replace(cfg.real, effects=[effect("coulomb_friction", "nope", force=1.0)])
    with pytest.raises(ValueError, match=allowed):
        make_plant(real, cfg.env)


def test_the_mujoco_spec_writes_the_native_effects_to_mjcf(env_cfg):
    effects = [
        effect("coulomb_friction", "slider", force=20.0),
        effect("viscous_damping", "hinge", coefficient=0.5),
        effect("actuator_gain", "slide", gain=1.5),
        effect("actuator_lag", "slide", time_constant=0.1),
        effect("mass_scale", "pole", scale=2.0),
        effect("actuator_offset", "slide", offset=0.3),
    ]  # not native: not in the MJCF
    nominal = load_spec(env_cfg.xml, env_cfg.timestep).compile()
    spec = mujoco_spec(env_cfg, effects, 0.5)
    model = spec.compile()
    # to_xml writes 6 significant digits (the pole's length): 1e-6 of its mass
    written = mujoco.MjSpec.from_string(spec.to_xml()).compile()
    for field in (
        "body_mass",
        "body_inertia",
        "dof_frictionloss",
        "dof_damping",
        "actuator_gear",
        "actuator_dyntype",
        "actuator_dynprm",
    ):
        np.testing.assert_allclose(getattr(written, field), getattr(model, field), rtol=1e-5)
    np.testing.assert_allclose(model.dof_frictionloss, [10.0, 0.0])  # friction gap 0.5
    np.testing.assert_allclose(model.dof_damping, nominal.dof_damping + [0.0, 0.5 * 0.5])
    np.testing.assert_allclose(model.actuator_gear[0, 0], 1.5 * nominal.actuator_gear[0, 0])
    assert model.actuator_dyntype[0] == mujoco.mjtDyn.mjDYN_FILTEREXACT
    np.testing.assert_allclose(model.actuator_dynprm[0, 0], 0.1)
    np.testing.assert_allclose(model.body_mass, nominal.body_mass * [1, 1, 2])
    np.testing.assert_allclose(model.body_inertia, nominal.body_inertia * [[1], [1], [2]])
    np.testing.assert_allclose(model.actuator_ctrlrange, nominal.actuator_ctrlrange)


def test_a_heavy_friction_holds_the_cart_in_the_simulator_as_in_the_plant():
    """80 N of friction against a 30 N push stops a sliding cart within a step, and it stays
    (C MuJoCo creeps at ~0.006 m/s). A tanh law sharper than one substep can stop (h F k w = 5
    at k = 50) overshot rest and chattered at +-0.14 m/s, so stick phases fit a friction too
    weak; the simulator's law is capped at the stable sharpness (h F k w = 2)."""
    from hds.effects import EffectSpec
    from hds.envs.system import make_simulator

    force, push = 80.0, 0.3  # push: 30 N through the slide's gear of 100
    sim, params = make_simulator(
        "cartpole.xml",
        "analytic",
        frames=2,
        effects=[EffectSpec("coulomb_friction", "slider", {"force": force})],
    )
    state = sim.init(np.array([0.0, HANG], np.float32), np.array([0.3, 0.0], np.float32))
    speeds = []
    step = jax.jit(lambda s: sim.step(params, s, np.full(sim.n_act, push, np.float32)))
    for _ in range(30):
        state = step(state)
        speeds.append(float(state.qd[0]))
    spec = load_spec("cartpole.xml")
    spec.joint("slider").frictionloss = force
    model = spec.compile()
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = [0.0, HANG], [0.3, 0.0]
    data.ctrl[:] = push
    plant = []
    for _ in range(30):
        mujoco.mj_step(model, data, nstep=2)
        plant.append(data.qvel[0])
    assert max(plant[1:]) < 0.01  # the plant holds it
    assert min(speeds) > 0, speeds  # the simulator's cart never reverses: no chatter
    assert max(speeds[1:]) < 0.05, speeds
