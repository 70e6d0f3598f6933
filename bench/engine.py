"""Section `engine`: the tree engine against brax generalized and MJX on every shipped system.

Per system and backend, in one process: the compile time (lower + compile) of a gradient
rollout (value_and_grad of a 100-step return w.r.t. the actions, batch 64 via vmap), and its
env steps per second forward (the rollout alone) and forward + backward. MJX runs with
`opt.iterations=1` (hds.envs.system sets it: its default solver loop rejects reverse mode).
`random4` is a generated tree of 4 joints (`random_tree_xml(0, 4)`): the issue's 4-DoF model.
Rows of systems and backends a run does not measure are carried over from the committed
results (generalized and MJX take an hour), each with a note of when and how it was measured.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from bench.common import best_of, block, load_results, timed

DEFAULT_BUDGET = {
    "systems": ["cartpole", "pendulum", "double_cartpole", "furuta", "acrobot", "random4"],
    "backends": ["tree", "analytic", "generalized", "mjx"],
    "batch": 64,
    "horizon": 100,
    "repeats": 3,
}


COLUMNS = [
    "system",
    "backend",
    "dofs",
    "grad compile s",
    "grad compile CPU s",
    "fwd env-steps/s",
    "fwd+bwd env-steps/s",
    "note",
]


def random_tree_xml(seed: int, joints: int) -> str:
    """An MJCF of a random kinematic tree of hinge and slide joints (one per body), with
    skewed frames, axes, anchors and inertias, damping, armature, stiffness, some joints
    limited, and a motor on two of them. No geom can collide (contype = conaffinity = 0)."""
    rng = np.random.default_rng(seed)

    def vec(scale=1.0, n=3):
        return " ".join(f"{x:.4f}" for x in rng.uniform(-scale, scale, n))

    children: dict[int, list[int]] = {i: [] for i in range(-1, joints)}
    for i in range(joints):
        children[int(rng.integers(-1, i))].append(i)

    def body(i: int) -> str:
        kind = "slide" if rng.random() < 0.3 else "hinge"
        limited = rng.random() < 0.5
        span = rng.uniform(0.3, 0.8) if kind == "slide" else rng.uniform(0.5, 1.5)
        limit = f'limited="true" range="{-span:.3f} {span:.3f}"' if limited else ""
        quat = rng.normal(size=4)
        iquat = rng.normal(size=4)
        inertia = rng.uniform(0.03, 0.05, 3)  # any two sum to more than the third
        inner = "".join(body(c) for c in children[i])
        return (
            f'<body name="b{i}" pos="{vec(0.4)}" quat="{" ".join(f"{x:.4f}" for x in quat)}">'
            f'<joint name="j{i}" type="{kind}" axis="{vec()}" pos="{vec(0.1)}" {limit} '
            f'damping="{rng.uniform(0, 0.3):.3f}" armature="{rng.uniform(0, 0.05):.3f}" '
            f'stiffness="{rng.uniform(0, 0.5):.3f}"/>'
            f'<inertial pos="{vec(0.2)}" quat="{" ".join(f"{x:.4f}" for x in iquat)}" '
            f'mass="{rng.uniform(0.3, 1.5):.3f}" '
            f'diaginertia="{" ".join(f"{x:.4f}" for x in inertia)}"/>'
            f'<geom type="sphere" size="0.05" contype="0" conaffinity="0"/>{inner}</body>'
        )

    motors = "".join(
        f'<motor name="m{j}" joint="j{j}" gear="{rng.uniform(1, 5):.2f}" ctrllimited="true" '
        'ctrlrange="-1 1"/>'
        for j in sorted(rng.choice(joints, size=min(2, joints), replace=False))
    )
    world = "".join(body(c) for c in children[-1])
    return (
        f'<mujoco><option timestep="0.005" gravity="{vec(3, 2)} -9.81"/>'
        f"<worldbody>{world}</worldbody><actuator>{motors}</actuator></mujoco>"
    )


def system_xml(name: str, folder: Path) -> str:
    """The MJCF of a system: an asset, or `randomN` (a generated tree of N joints)."""
    if name.startswith("random"):
        path = folder / f"{name}.xml"
        path.write_text(random_tree_xml(0, int(name.removeprefix("random"))))
        return str(path)
    return f"{name}.xml"


def rollouts(sim, params, batch: int, horizon: int):
    """(jitted forward rollout, jitted value_and_grad) of a batch of open-loop returns."""

    def ret(u, q0, qd0):
        def body(state, ut):
            state = sim.step(params, state, ut)
            return state, -jnp.sum(state.q**2) - 0.01 * jnp.sum(state.qd**2)

        return jax.lax.scan(body, sim.init(q0, qd0, params), u)[1].sum()

    def total(u, q0, qd0):
        return jax.vmap(ret)(u, q0, qd0).mean()

    return jax.jit(total), jax.jit(jax.value_and_grad(total))


def measure(xml: str, backend: str, budget: dict) -> dict:
    from hds.envs.system import make_simulator

    sim, params = make_simulator(xml, backend)
    b, t = budget["batch"], budget["horizon"]
    rng = np.random.default_rng(0)
    u = jnp.asarray(rng.uniform(-0.5, 0.5, (b, t, sim.n_act)) * sim.ctrl_range[:, 1], jnp.float32)
    q0 = jnp.asarray(rng.uniform(-0.2, 0.2, (b, sim.nq)), jnp.float32)
    qd0 = jnp.zeros((b, sim.nq), jnp.float32)
    forward, grad = rollouts(sim, params, b, t)
    cpu = time.process_time()
    with timed() as compile_grad:
        grad = grad.lower(u, q0, qd0).compile()
    cpu = time.process_time() - cpu
    forward = forward.lower(u, q0, qd0).compile()
    fwd_s, _ = best_of(lambda: block(forward(u, q0, qd0)), budget["repeats"])
    bwd_s, _ = best_of(lambda: block(grad(u, q0, qd0)), budget["repeats"])
    value = float(forward(u, q0, qd0))
    return {
        "compile_s": compile_grad.s,
        "compile_cpu_s": cpu,
        "fwd_steps_per_s": b * t / fwd_s,
        "grad_steps_per_s": b * t / bwd_s,
        "finite": bool(np.isfinite(value)),
        "dofs": sim.nq,
    }


def carried(measured: set[tuple[str, str]]) -> tuple[list[list], dict[str, str]]:
    """The committed results' rows of the (system, backend) pairs this run does not measure,
    and where each was measured ('system/backend': 'when, load, command')."""
    earlier = load_results().get("sections", {}).get("engine", {})
    if not earlier.get("tables"):
        return [], {}
    here = (
        f"{earlier.get('measured_at')} under load {earlier.get('load_before')} / "
        f"{earlier.get('load_after')} by `{earlier.get('command')}`"
    )
    table = earlier["tables"][0]
    rows = [dict(zip(table["columns"], r, strict=True)) for r in table["rows"]]
    rows = [
        [r.get(c, "-") for c in COLUMNS]
        for r in rows
        if (r["system"], r["backend"]) not in measured
    ]
    origins = earlier.get("origins", {})
    return rows, {f"{r[0]}/{r[1]}": origins.get(f"{r[0]}/{r[1]}", here) for r in rows}


def carried_notes(origins: dict[str, str]) -> list[str]:
    by_origin: dict[str, list[str]] = {}
    for pair, origin in origins.items():
        by_origin.setdefault(origin, []).append(pair)
    return [
        f"Rows {', '.join(pairs)}: carried over, measured {origin}; compare backends within "
        "one run's load."
        for origin, pairs in by_origin.items()
    ]


def run(budget: dict) -> dict:
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for system in budget["systems"]:
            xml = system_xml(system, Path(folder))
            for backend in budget["backends"]:
                try:
                    m = measure(xml, backend, budget)
                except ValueError as err:  # a backend that refuses the model says why
                    rows.append([system, backend, *["-"] * (len(COLUMNS) - 3), str(err)[:60]])
                    continue
                rows.append(
                    [
                        system,
                        backend,
                        m["dofs"],
                        m["compile_s"],
                        m["compile_cpu_s"],
                        m["fwd_steps_per_s"],
                        m["grad_steps_per_s"],
                        "" if m["finite"] else "non-finite return",
                    ]
                )
    b, t = budget["batch"], budget["horizon"]
    earlier, origins = carried({(r[0], r[1]) for r in rows})
    order = {name: i for i, name in enumerate(DEFAULT_BUDGET["systems"])}
    rows = sorted(rows + earlier, key=lambda r: order.get(r[0], len(order)))
    # the target reads a carried-over row too: a partial rerun keeps what was measured
    four = [r for r in rows if r[:2] == ["random4", "tree"] and r[3] != "-"]
    return {
        "title": "physics engines: the tree engine vs brax generalized and MJX",
        "tables": [
            {
                "caption": f"Gradient rollout, {t} steps x batch {b} (vmap), float32; compile = "
                "lower + compile of value_and_grad (wall, and this process's CPU seconds: on a "
                "shared machine the wall time also counts the others' turns on the cores); "
                "env steps/s = batch x horizon / median call",
                "columns": COLUMNS,
                "rows": rows,
            }
        ],
        "targets": [
            {
                "target": "tree: 100-step batch-64 grad rollout of a 4-DoF model compiles < 10 s",
                "value": next((f"{r[3]:.1f} s ({r[4]:.1f} CPU s)" for r in four), "not run"),
                "met": next((r[3] < 10 for r in four), None),
            }
        ],
        "origins": origins,
        "notes": carried_notes(origins),
    }
