"""`python -m experiments.excitation_design.ceiling`: how much plant time any open-loop signal
of the amplitude bound could save over the PRBS, on the model (the fit's simulator at the true
values, the true sensor noise, `Designer.predicted_se_of`): PRBS of several bit lengths and
square waves of several half periods (bang-bang at the bound, the shape a Coulomb force's and a
gain's information favour), within the rail. Prints a markdown table.
"""

from __future__ import annotations

import numpy as np
from omegaconf import OmegaConf
from scipy import stats

from experiments.excitation_design.__main__ import AMPLITUDE, CASES, CONF, worst
from hds.config import env_config
from hds.data.excitation import excitation
from hds.discover.design import get_designer, limits_of
from hds.discover.workflow import fit_backend, with_backend
from hds.envs import make_env
from hds.utils.runtime import enable_compilation_cache

EPISODES = 16


def signals(env, steps, dt, high):
    ctrl = np.asarray(env.sim.ctrl_range)
    out = {}
    for bits in (1, 2, 4, 8, 16):
        out[f"PRBS, bit {bits} steps"] = excitation(
            "prbs", 1, EPISODES, steps, dt, ctrl, scale=AMPLITUDE, bit_time=bits * dt
        )
    t = np.arange(steps)
    for half in (5, 10, 25, 50):
        sq = np.where((t // half) % 2 == 0, high, -high)[None, :, None]
        out[f"square, half period {half} steps"] = np.repeat(sq, EPISODES, axis=0)
    out["random steps"] = excitation("steps", 1, EPISODES, steps, dt, ctrl, scale=AMPLITUDE)
    out["chirp"] = excitation("chirp", 1, EPISODES, steps, dt, ctrl, scale=AMPLITUDE)
    return out


def setup(name):
    """A case's designer, limits, initial state, true values {key: {param: value}} and the
    true values in the designer's label order."""
    spec = CASES[name]
    env_cfg = env_config(
        OmegaConf.to_container(OmegaConf.load(CONF / "env" / f"{spec['env']}.yaml"))
    )
    fit_cfg = with_backend(env_cfg, fit_backend(env_cfg, "auto"))
    env = make_env(env_cfg)
    steps, dt = int(env.task.horizon), float(env.sim.dt)
    designer = get_designer(fit_cfg, spec["keys"], dt, steps, horizon=10)
    limits = limits_of(fit_cfg, AMPLITUDE)
    x0 = np.concatenate([spec["rest"], np.zeros(env.sim.n_obs - env.sim.nq)])
    truth = {}
    for e in spec["real"]["effects"]:
        gap = spec["real"]["friction_gap"] if e["name"] == "coulomb_friction" else 1.0
        truth[f"{e['name']}@{e['target']}"] = {p: v * gap for p, v in e["params"].items()}
    values = [truth[k.rsplit(".", 1)[0]][k.rsplit(".", 1)[1]] for k in designer.labels]
    return env, designer, limits, x0, truth, values


def main():
    enable_compilation_cache()
    lines = [
        "| case | signal | predicted plant time / PRBS (bit 4)'s | within the rail |",
        "| --- | --- | --- | --- |",
    ]
    for name in ("friction80", "friction_gain"):
        spec = CASES[name]
        env, designer, limits, x0, truth, values = setup(name)
        steps, dt = int(env.task.horizon), float(env.sim.dt)
        t_q = stats.t.ppf(0.975, EPISODES - 1) / np.sqrt(EPISODES)
        times = {}
        for label, u in signals(env, steps, dt, limits.u_high[0]).items():
            se = designer.predicted_se_of(truth, u, x0, spec["noise"])
            ratio = worst(values, t_q * se, designer.labels, spec["targets"])
            rail = all(
                max(limits.violation(designer.open_loop(truth, ue, x0), ue).values()) <= 0
                for ue in u
            )
            times[label] = (ratio**2, rail)
        ref = times["PRBS, bit 4 steps"][0]
        for label, (t, rail) in times.items():
            lines.append(f"| {name} | {label} | {t / ref:.2f} | {'yes' if rail else 'no'} |")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
