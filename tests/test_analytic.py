"""The analytic backend (hds/envs/analytic.py) against brax generalized and C MuJoCo.

Every jitted function is compiled once per session (module-level caches; one batch shape, and
effect parameters are an argument, so nominal and modified physics share one compile).

Stated tolerances, over 0.5 s of open-loop input from random states (pole hanging included):
  - analytic vs C MuJoCo 3.17 (mj_step, same ctrl): |dq| <= 1e-4, |dqd| <= 1e-3, also through
    the slider's limit (observed: 1e-6 and 5e-6 in free motion, 6e-6 and 5e-5 pressing
    into the limit: float32 round-off);
  - analytic vs brax generalized with an exact mass-matrix inverse (matrix_inv_iterations=0,
    which also makes brax treat damping implicitly, as MuJoCo): the same tolerances;
  - analytic vs brax generalized as the MJCF configures it (10 iterations of an approximate
    inverse, explicit damping): |dq| <= 0.25, |dqd| <= 1.0 (observed over 64 rollouts of the
    cart-pole: 7 mm, 0.11 rad, 0.08 m/s, 0.41 rad/s; the exact-inverse run above shows the
    difference is brax's approximation, not the analytic model).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from hds.envs import analytic
from hds.envs.system import make_simulator, resolve_xml

B = 8  # rollouts per batch; one shape for every call
Q_TOL, QD_TOL = 1e-4, 1e-3  # against MuJoCo and exact-inverse generalized
Q_LOOSE, QD_LOOSE = 0.25, 1.0  # against generalized as configured


def effect(name, target, **params):
    return {"name": name, "target": target, "params": params}


# asset: frames per step, the body and actuator effects act on, modified effect values
ASSETS = {
    "cartpole.xml": dict(frames=2, body="pole", actuator="slide", scale=1.6, gain=0.7),
    "pendulum.xml": dict(frames=1, body="pole", actuator="torque", scale=1.4, gain=0.6),
}


def with_values(params, scale, gain):
    """The simulator's effect parameters (mass_scale first, actuator_gain second) set."""
    return ({"scale": jnp.float32(scale)}, {"gain": jnp.float32(gain)})


def batched_rollout(sim):
    """jit(params, q0 [B,nq], qd0 [B,nq], u [B,T,1]) -> [B,T,2nq] states after each step."""

    def one(params, q0, qd0, u):
        def body(state, ut):
            state = sim.step(params, state, ut)
            return state, jnp.concatenate([state.q, state.qd])

        return jax.lax.scan(body, sim.init(q0, qd0, params), u)[1]

    return jax.jit(jax.vmap(one, in_axes=(None, 0, 0, 0)))


def mujoco_rollout(xml, q0, qd0, u, frames, body=None, scale=1.0, actuator=None, gain=1.0):
    """C MuJoCo from the same MJCF (no force motors), mass and gear scaled as the effects do."""
    model = mujoco.MjModel.from_xml_path(str(resolve_xml(xml)))
    if body is not None:
        model.body_mass[model.body(body).id] *= scale
        model.body_inertia[model.body(body).id] *= scale
    if actuator is not None:
        model.actuator_gear[model.actuator(actuator).id, 0] *= gain
    data = mujoco.MjData(model)
    out = np.zeros((len(q0), u.shape[1], 2 * model.nq))
    for b in range(len(q0)):
        mujoco.mj_resetData(model, data)
        data.qpos[:], data.qvel[:] = q0[b], qd0[b]
        for t in range(u.shape[1]):
            data.ctrl[:] = u[b, t]
            for _ in range(frames):
                mujoco.mj_step(model, data)
            out[b, t] = np.concatenate([data.qpos, data.qvel])
    return out


class Case:
    """One asset: its simulators (analytic, generalized, generalized with an exact inverse),
    each compiled once, and random open-loop inputs over 0.5 s."""

    def __init__(self, xml):
        self.xml, self.cfg = xml, ASSETS[xml]
        c = self.cfg
        effects = [effect("mass_scale", c["body"]), effect("actuator_gain", c["actuator"])]
        self.sims = {}
        for backend in ("analytic", "generalized"):
            self.sims[backend], self.params = make_simulator(
                xml, backend, frames=c["frames"], effects=effects
            )
        gen = self.sims["generalized"]
        self.sims["exact"] = gen.with_sys(gen.sys.replace(matrix_inv_iterations=0))
        self.fns = {}
        self.sim = self.sims["analytic"]
        self.nq = self.sim.nq
        self.steps = math.ceil(0.5 / self.sim.dt - 1e-9)
        self.hi = float(self.sim.ctrl_range[0, 1])
        rng = np.random.default_rng(0)
        q0 = rng.uniform(-1, 1, (B, self.nq)) * np.array([2.0, np.pi])[-self.nq :]
        q0[:2, -1] = np.pi  # the pole hanging down: still, and moving
        qd0 = rng.normal(size=(B, self.nq))
        qd0[0] = 0.0
        # inputs beyond the ctrl range too, so clipping is compared as well
        u = rng.uniform(-1.3, 1.3, (B, self.steps, 1)) * self.hi
        self.free = (q0.astype(np.float32), qd0.astype(np.float32), u.astype(np.float32))

    def run(self, backend, data, scale=1.0, gain=1.0):
        if backend not in self.fns:
            self.fns[backend] = batched_rollout(self.sims[backend])
        return np.array(self.fns[backend](with_values(self.params, scale, gain), *data))

    def mujoco(self, data, scale=1.0, gain=1.0):
        c = self.cfg
        return mujoco_rollout(self.xml, *data, c["frames"], c["body"], scale, c["actuator"], gain)


_CASES: dict[str, Case] = {}


def get_case(xml: str) -> Case:
    if xml not in _CASES:
        _CASES[xml] = Case(xml)
    return _CASES[xml]


@pytest.fixture(params=list(ASSETS))
def case(request):
    return get_case(request.param)


@pytest.fixture
def cartpole():
    return get_case("cartpole.xml")


def deviation(a, b, nq):
    """Largest |a - b| over the q part and over the qd part."""
    err = np.abs(a - b).reshape(-1, 2 * nq)
    return float(err[:, :nq].max()), float(err[:, nq:].max())


def test_matches_mujoco(case):
    dq, dqd = deviation(case.run("analytic", case.free), case.mujoco(case.free), case.nq)
    assert dq <= Q_TOL and dqd <= QD_TOL, (dq, dqd)


def test_matches_generalized(case):
    ours = case.run("analytic", case.free)
    dq, dqd = deviation(ours, case.run("exact", case.free), case.nq)
    assert dq <= Q_TOL and dqd <= QD_TOL, ("exact inverse", dq, dqd)
    dq, dqd = deviation(ours, case.run("generalized", case.free), case.nq)
    assert dq <= Q_LOOSE and dqd <= QD_LOOSE, ("as configured", dq, dqd)


def test_effects_change_dynamics_like_generalized(case):
    c = case.cfg
    nominal = case.run("analytic", case.free)
    ours = case.run("analytic", case.free, c["scale"], c["gain"])
    theirs = case.run("exact", case.free, c["scale"], c["gain"])
    reference = case.mujoco(case.free, c["scale"], c["gain"])
    moved = deviation(ours, nominal, case.nq)
    assert min(moved) > 100 * QD_TOL, f"the effects barely change the motion: {moved}"
    dq, dqd = deviation(ours, theirs, case.nq)
    assert dq <= Q_TOL and dqd <= QD_TOL, ("vs generalized", dq, dqd)
    dq, dqd = deviation(ours, reference, case.nq)
    assert dq <= Q_TOL and dqd <= QD_TOL, ("vs MuJoCo with scaled mass and gear", dq, dqd)
    # generalized as configured: the effects move both backends' trajectories alike
    change = case.run("generalized", case.free, c["scale"], c["gain"])
    change -= case.run("generalized", case.free)
    dq, dqd = deviation(ours - nominal, change, case.nq)
    assert dq <= Q_LOOSE and dqd <= QD_LOOSE, ("change vs generalized as configured", dq, dqd)


def test_slider_limit_matches_mujoco(cartpole):
    """Driven into the rail's end at +-10: MuJoCo's soft limit, with its refsafe time constant."""
    q0, qd0, u = (x.copy() for x in cartpole.free)
    side = np.where(np.arange(B) % 2 == 0, 1.0, -1.0)
    q0[:, 0] = side * np.linspace(9.5, 9.95, B)
    qd0[:, 0] = side * np.linspace(1.0, 5.0, B)
    u[:, :, 0] = side[:, None] * np.abs(u[:, :, 0])  # pushing into the limit, clipped at 3
    data = (q0, qd0, u)
    ours, reference = cartpole.run("analytic", data), cartpole.mujoco(data)
    assert np.abs(reference[:, :, 0]).max() > 10.0  # the limit is reached
    assert np.abs(ours[:, :, 0]).max() < 10.2  # and holds
    dq, dqd = deviation(ours, reference, 2)
    assert dq <= Q_TOL and dqd <= QD_TOL, (dq, dqd)


# -- gradients ----------------------------------------------------------------------------


_GRADS: dict[str, tuple] = {}


def grad_case(xml: str):
    """(simulator, jitted value_and_grad of a 20-step return w.r.t. the actions), built once."""
    if xml in _GRADS:
        return _GRADS[xml]
    sim, params = make_simulator(xml, "analytic", frames=ASSETS[xml]["frames"])

    def ret(u, q0, qd0, weight):
        """Upright pole, small velocities, and `weight` times the first joint's displacement
        (at the limit: how deep the cart presses into it, which the control sets)."""

        def body(state, ut):
            state = sim.step(params, state, ut)
            q, qd = state.q, state.qd
            reward = jnp.cos(q[-1]) - 0.01 * jnp.sum(qd**2) + weight * (q[0] - q0[0])
            return state, reward

        return jax.lax.scan(body, sim.init(q0, qd0), u)[1].sum()

    _GRADS[xml] = sim, jax.jit(jax.value_and_grad(ret))
    return _GRADS[xml]


@pytest.mark.parametrize(
    "xml, start",
    [("cartpole.xml", "swinging"), ("pendulum.xml", "swinging"), ("cartpole.xml", "at_limit")],
)
def test_gradient_matches_finite_differences(xml, start):
    sim, value_and_grad = grad_case(xml)
    rng = np.random.default_rng(1)
    hi = float(sim.ctrl_range[0, 1])
    u = jnp.asarray(rng.uniform(-0.8, 0.8, (20, 1)) * hi, jnp.float32)  # inside the ctrl range
    if start == "swinging":
        q0 = jnp.asarray([0.3, 2.5][-sim.nq :], jnp.float32)
        qd0 = jnp.asarray([0.5, -1.0][-sim.nq :], jnp.float32)
        weight = jnp.float32(1.0)
    else:  # in the slider's limit, pushed into it for the whole rollout
        q0, qd0 = jnp.asarray([10.02, 2.5]), jnp.asarray([0.5, 1.0])
        u = jnp.abs(u) * 0.5 + 1.0
        weight = jnp.float32(100.0)
    _, grad = value_and_grad(u, q0, qd0, weight)
    assert bool(jnp.isfinite(grad).all())
    # At the limit the cart sits about 2 mm deep in it (MuJoCo's soft limit), and float32
    # round-off of q = 10 is 1e-6 m: a larger step, along directions that all push harder.
    eps = 1e-2 if start == "swinging" else 1e-1
    for k in range(3):
        v = rng.normal(size=u.shape)
        v = jnp.asarray(v if start == "swinging" else np.abs(v), jnp.float32)
        v = v / jnp.linalg.norm(v)
        up, _ = value_and_grad(u + eps * v, q0, qd0, weight)
        down, _ = value_and_grad(u - eps * v, q0, qd0, weight)
        fd = float(up - down) / (2 * eps)
        ad = float(jnp.sum(grad * v))
        assert abs(ad - fd) <= 2e-2 * abs(fd) + 1e-3, (k, ad, fd)


# -- models the analytic backend refuses, and generality within what it accepts -------------

DOUBLE_PENDULUM = """<mujoco><worldbody><body name="a"><joint name="h1" axis="0 1 0"/>
  <geom type="capsule" fromto="0 0 0 0 0 0.5" size="0.03" contype="0" conaffinity="0"/>
  <body name="b" pos="0 0 0.5"><joint name="h2" axis="0 1 0"/>
  <geom type="capsule" fromto="0 0 0 0 0 0.5" size="0.03" contype="0" conaffinity="0"/>
  </body></body></worldbody><actuator><motor joint="h1" name="m"/></actuator></mujoco>"""

COLLIDING = """<mujoco><worldbody><geom name="floor" type="plane" size="5 5 0.1" pos="0 0 -1"/>
  <body name="pole"><joint name="hinge" axis="0 1 0"/>
  <geom type="capsule" fromto="0 0 0 0 0 0.5" size="0.03"/></body>
  </worldbody><actuator><motor joint="hinge" name="m"/></actuator></mujoco>"""

FREE_BODY = """<mujoco><worldbody><body name="box"><freejoint/>
  <geom type="box" size="0.1 0.1 0.1" contype="0" conaffinity="0"/></body>
  </worldbody></mujoco>"""


@pytest.mark.parametrize(
    "xml, why", [(DOUBLE_PENDULUM, "joints"), (COLLIDING, "collide"), (FREE_BODY, "joints")]
)
def test_unsupported_model_raises_a_clear_error(tmp_path, xml, why):
    path = tmp_path / "model.xml"
    path.write_text(xml)
    with pytest.raises(ValueError, match="use backend=generalized") as err:
        make_simulator(str(path), "analytic")
    assert why in str(err.value)
    make_simulator(str(path), "generalized")  # the way out the message names


def test_other_integrators_are_refused(tmp_path):
    path = tmp_path / "model.xml"
    path.write_text(
        resolve_xml("pendulum.xml").read_text().replace("<option ", '<option integrator="RK4" ')
    )
    with pytest.raises(ValueError, match="integrator='Euler'"):
        make_simulator(str(path), "analytic")


# Both structures with nothing aligned: rotated bodies, a slide axis with a vertical part, a
# hinge axis not perpendicular to the pole, a COM off the axis, a hinge anchor away from the
# body origin, armature, stiffness, and a limited hinge that the pendulum swings into (with a
# direct stiffness and damping, and a wide impedance curve, for its soft limit). The
# cart-pole keeps MuJoCo's default contype: a parent and its child never collide, so it is accepted.
SKEWED_CARTPOLE = """<mujoco><compiler angle="radian"/><option timestep="0.01"/>
  <worldbody><body name="cart" pos="0.1 0.2 0.3" quat="0.9 0.1 0.3 0.2">
    <joint name="slider" type="slide" axis="1 0 0.4" range="-1 1" damping="0.5" armature="0.2"/>
    <geom type="box" size="0.2 0.1 0.1" pos="0.05 0 0.02"/>
    <body name="pole" pos="0 0.1 0.05" quat="0.95 0.2 0 0.1">
      <joint name="hinge" axis="0.2 1 0.1" pos="0 0.02 0.03" damping="0.3" armature="0.01"
             stiffness="0.8"/>
      <geom type="capsule" fromto="0.05 0 0 0.1 0.03 0.7" size="0.04"/></body></body></worldbody>
  <actuator><motor joint="slider" name="slide" gear="30" ctrlrange="-2 2" ctrllimited="true"/>
  </actuator></mujoco>"""

SKEWED_PENDULUM = """<mujoco><compiler angle="radian"/><option timestep="0.005"/>
  <default><geom contype="0" conaffinity="0"/></default>
  <worldbody><body name="pole" pos="0 0 1" quat="0.8 0.3 0.2 0.1">
    <joint name="hinge" axis="0.1 1 0.3" pos="0.02 0 0.05" range="-1 1" damping="0.1"
           armature="0.02" solreflimit="-800 -20" solimplimit="0.8 0.9 0.1 0.3 3"/>
    <geom type="capsule" fromto="0.03 0.01 0 0.05 0 0.6" size="0.03"/>
    <geom type="sphere" size="0.06" pos="0 0.05 0.6"/></body></worldbody>
  <actuator><motor joint="hinge" name="torque" gear="3" ctrlrange="-1 1" ctrllimited="true"/>
  </actuator></mujoco>"""


@pytest.mark.parametrize("xml", [SKEWED_CARTPOLE, SKEWED_PENDULUM])
def test_general_geometry_matches_mujoco(tmp_path, xml):
    path = tmp_path / "model.xml"
    path.write_text(xml)
    sim, params = make_simulator(str(path), "analytic")
    nq, steps = sim.nq, round(0.5 / sim.dt)
    rng = np.random.default_rng(2)
    q0 = rng.uniform(-0.8, 0.8, (B, nq)).astype(np.float32)
    qd0 = rng.normal(size=(B, nq)).astype(np.float32) * 4
    u = rng.uniform(-1.5, 1.5, (B, steps, 1)).astype(np.float32) * sim.ctrl_range[0, 1]
    ours = np.asarray(batched_rollout(sim)(params, q0, qd0, u))
    reference = mujoco_rollout(str(path), q0, qd0, u, 1)
    assert np.abs(reference[:, :, 0]).max() > 1.0  # a limit is reached
    dq, dqd = deviation(ours, reference, nq)
    assert dq <= Q_TOL and dqd <= QD_TOL, (dq, dqd)


def test_check_names_the_structure():
    for xml, structure in (("cartpole.xml", "cartpole"), ("pendulum.xml", "pendulum")):
        sim, _ = make_simulator(xml, "analytic")
        assert analytic.check(sim.sys) == structure
        assert sim.pipeline is analytic
