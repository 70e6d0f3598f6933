"""Issue 42 probes: discovery on C MuJoCo cart-pole records with a hinge spring, rail friction
+ hinge damping, and rail friction + gain + delay (records as tests/test_discover.py makes them).

    PYTHONPATH=$PWD python experiments/discovery_issue42/probe.py \
        spring 2,5,20 wide 2,5 t3 20,5 two three
"""

import dataclasses
import sys
import time

sys.path.insert(0, "tests")  # the tests' record helpers
import numpy as np
from conftest import make_config
from test_discover import CFG, Plants, effect, record

from hds.discover import discover
from hds.envs import make_env
from hds.real.mujoco_plant import MujocoPlant

env_cfg = make_config("env.backend=analytic").env
task = make_env(env_cfg).task
plants = Plants(env_cfg)


def show(tag, res):
    print("==", tag)
    for e in res.missing_effects:
        print("  named", e.name, e.target, e.fitted(), f"{e.explained_fraction:.4f}")
    for e in res.law_mismatch:
        print("  mismatch", e.name, e.target, e.fitted(), f"{e.explained_fraction:.4f}")
    for e in res.tentative:
        print("  tentative", e.name, e.target, e.fitted())
    for t in res.terms:
        print("  term", t.describe())
    print("  stopped", res.stopped, "unexpl", res.unexplained_fraction)
    print(
        "  err",
        res.error("before").normalized,
        res.error("after").normalized,
        res.after_terms["heldout"][1].normalized if res.after_terms else None,
    )
    print(
        "  states",
        [
            (sorted(s.keys), round(s.heldout_error, 5), round(s.misfit, 1))
            for s in res.selection.states
        ],
    )
    print(
        "  mismatchstates",
        [
            (m.selected[-1].key, round(m.heldout_error, 5), round(w.heldout_error, 5))
            for m, w in res.selection.mismatch
        ],
    )
    print("  dropped", [c.key for c in res.selection.dropped])


which = sys.argv[1:]
if "spring" in which:
    from hds.envs.system import load_spec

    for k in [float(x) for x in (sys.argv[sys.argv.index("spring") + 1]).split(",")]:
        spec = load_spec(env_cfg.xml)
        spec.joint("hinge").stiffness[0] = k
        path = f"/tmp/h42/cp_spring_{k}.xml"
        open(path, "w").write(spec.to_xml())
        plant = MujocoPlant(dataclasses.replace(env_cfg, xml=path))
        data = record(plant, task)
        q = data.obs[..., 1]
        print("hinge span", q.min(), q.max(), "per-ep max", np.max(q.max(1) - q.min(1)))
        t = time.time()
        res = discover(data, env_cfg, CFG)
        print("t", time.time() - t)
        show(f"spring {k}", res)
if "two" in which:
    hidden = [
        effect("coulomb_friction", "slider", force=18.0),
        effect("viscous_damping", "hinge", coefficient=0.3),
    ]
    for seed in (0, 1, 3):
        t = time.time()
        res = discover(record(plants("mujoco", hidden), task, seed=seed), env_cfg, CFG)
        print("t", time.time() - t)
        show(f"two seed {seed}", res)
if "three" in which:
    hidden = [
        effect("coulomb_friction", "slider", force=18.0),
        effect("actuator_gain", "slide", gain=0.85),
        effect("action_delay", "slide", steps=1),
    ]
    for seed in (0, 1, 3):
        t = time.time()
        res = discover(record(plants("mujoco", hidden), task, seed=seed), env_cfg, CFG)
        print("t", time.time() - t)
        show(f"three seed {seed}", res)
if "noisy" in which:
    nz = float(sys.argv[sys.argv.index("noisy") + 1])
    H2 = [
        effect("coulomb_friction", "slider", force=18.0),
        effect("viscous_damping", "hinge", coefficient=0.3),
    ]
    H3 = [
        effect("coulomb_friction", "slider", force=18.0),
        effect("actuator_gain", "slide", gain=0.85),
        effect("action_delay", "slide", steps=1),
    ]
    for seed in range(4):
        for tag, hidden in (("two", H2), ("three", H3)):
            res = discover(
                record(plants("mujoco", hidden), task, seed=seed, noise=nz), env_cfg, CFG
            )
            show(f"{tag} noise {nz} seed {seed}", res)
if "wide" in which:
    from test_discover import E, T

    from hds.data import collect, random_steps
    from hds.envs.system import load_spec

    for k in [float(x) for x in (sys.argv[sys.argv.index("wide") + 1]).split(",")]:
        spec = load_spec(env_cfg.xml)
        spec.joint("hinge").stiffness[0] = k
        path = f"/tmp/h42/cp_spring_{k}.xml"
        open(path, "w").write(spec.to_xml())
        plant = MujocoPlant(dataclasses.replace(env_cfg, xml=path))
        rng = np.random.default_rng(0)
        q0 = np.c_[rng.uniform(-0.5, 0.5, E), rng.uniform(-2 * np.pi, 2 * np.pi, E)]
        qd0 = rng.uniform(-0.5, 0.5, (E, 2))
        u = random_steps(
            1, E, T, plant.dt, plant.ctrl_range, min_hold=0.1, max_hold=0.5, scale=0.15
        )
        data = collect(plant, task, q0, qd0, u)
        q = data.obs[..., 1]
        print("hinge span", q.min(), q.max())
        res = discover(data, env_cfg, CFG)
        show(f"wide spring {k}", res)
        print(res.angle_readings)
if "big" in which:
    import test_discover as td

    td.E, td.T = 24, 150
    f, c = (float(x) for x in sys.argv[sys.argv.index("big") + 1].split(","))
    H2 = [
        effect("coulomb_friction", "slider", force=f),
        effect("viscous_damping", "hinge", coefficient=c),
    ]
    H3 = [
        effect("coulomb_friction", "slider", force=f),
        effect("actuator_gain", "slide", gain=0.85),
        effect("action_delay", "slide", steps=1),
    ]
    for seed in range(2):
        for tag, hidden in (("two", H2), ("three", H3)):
            res = discover(td.record(plants("mujoco", hidden), task, seed=seed), env_cfg, CFG)
            show(f"big {tag} seed {seed}", res)
if "t3" in which:
    f, seed = sys.argv[sys.argv.index("t3") + 1].split(",")
    H3 = [
        effect("coulomb_friction", "slider", force=float(f)),
        effect("actuator_gain", "slide", gain=0.85),
        effect("action_delay", "slide", steps=1),
    ]
    res = discover(record(plants("mujoco", H3), task, seed=int(seed)), env_cfg, CFG)
    show(f"t3 {f} {seed}", res)
    for r in res.selection.rounds:
        best = sorted(r, key=lambda x: x["heldout_error"])[:4]
        print(
            [
                (b["name"], b["target"], b["params"], round(b["heldout_error"], 5), b["iterations"])
                for b in best
            ]
        )
if "nd" in which:
    h = [effect("viscous_damping", "hinge", coefficient=0.3)]
    res = discover(record(plants("mujoco", h), task, noise=0.01), env_cfg, CFG)
    show("noisy damping", res)
if "t3" in which:
    print(
        res.selection.final.keys,
        [
            (r["a"], r["b"], round(r["rho"], 4))
            for r in __import__("hds.discover.explain", fromlist=["x"]).correlations(
                res.selection.final
            )
        ],
    )
    print(res.warnings)
if "sl" in which:
    spec = __import__("hds.envs.system", fromlist=["x"]).load_spec(env_cfg.xml)
    spec.joint("slider").stiffness[0] = 30.0
    path = "/tmp/h42/cp_slider_spring.xml"
    open(path, "w").write(spec.to_xml())
    res = discover(record(MujocoPlant(dataclasses.replace(env_cfg, xml=path)), task), env_cfg, CFG)
    show("slider spring", res)
