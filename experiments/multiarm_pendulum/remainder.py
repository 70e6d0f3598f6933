"""What the double pendulum's k-step remainder is made of (README: "What the double's remainder
is made of"). Numpy plus hds's simulator, no discovery: the identification windows exactly as
discovery cuts them (Y_id at 10 ms, 1 s windows every 0.5 s, measured initial states, each
variable normalised by its std on Y_id), simulated at 1 ms from each window's first sample,
for the nominal model (the authors' parameters without damping), the published fit and a
Coulomb friction on arm1 (the value discovery selects); the squared normalised residual is then
split by variable, by step within the window and by window amplitude, beside the noise floor
discovery estimates (`hds.discover.data.noise_level`) and the velocities' own consistency with
the angles. `python experiments/multiarm_pendulum/remainder.py` (about a minute); writes
remainder.json beside this file."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

# XLA's C++ log (a notice per persistent-cache hit) is read when jax loads: quiet it first,
# as hds's commands do (hds/__init__.py sets it too, but jax is imported before hds here)
os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from hds.data import multiarm  # noqa: E402
from hds.discover.data import noise_level  # noqa: E402
from hds.envs.system import make_simulator  # noqa: E402
from hds.utils.io import atomic_write_json  # noqa: E402
from hds.utils.runtime import enable_compilation_cache  # noqa: E402

HERE = Path(__file__).resolve().parent
DATA = HERE.parents[1].parent / "shared" / "data" / "multiarm_pendulum"
FILE = DATA / "DoublePendulumDataForParameterEstimation.mat"
XML = "multiarm_double.xml"
DECIM, STRIDE = 10, 50  # discovery's 10 ms samples, a window every 0.5 s


def effects(model: str, coulomb: float) -> list[dict]:
    if model == "nominal":
        return []
    if model == "published":
        return multiarm.published_effects(2)
    return [{"name": "coulomb_friction", "target": "arm1", "params": {"force": coulomb}}]


def rollout(eff, x0: np.ndarray, steps: int) -> np.ndarray:
    """[B, steps+1, 4] joint coordinates every 1 ms from the joint states x0 [B, 4]."""
    sim, params = make_simulator(
        XML, backend="tree", timestep=1e-3, frames=1, effects=eff, sharpness=50.0
    )
    zero = jnp.zeros((sim.n_act,))

    @jax.jit
    def run(x):
        def one(x):
            s = sim.init(x[:2], x[2:], params)

            def body(s, _):
                s = sim.step(params, s, zero)
                return s, sim.observe(params, s)

            _, traj = jax.lax.scan(body, s, None, length=steps)
            return jnp.concatenate([x[None], traj])

        return jax.vmap(one)(x)

    return np.asarray(run(jnp.asarray(x0, jnp.float32)), np.float64)


def main(horizons=(100, 50, 20), coulomb=5.55e-4) -> dict:
    enable_compilation_cache()
    ident, held = multiarm.load(FILE)  # 1 ms, joint coordinates
    obs = ident.obs  # [E, T+1, 4]
    dec = obs[:, ::DECIM]
    scale = dec.reshape(-1, 4).std(axis=0)
    out = {"variables": list(multiarm.obs_names(2)), "scale": scale.tolist()}
    noise = noise_level(dec)
    out["noise_floor_over_std"] = (noise / scale).tolist()
    # the velocities against the encoders' angles: the angle's change over 20 ms against the
    # velocity's integral over the same 20 ms (both measured, no model): a mean-velocity error
    # of each joint; the authors de-noised the velocities (median filter, wavelets), the angles
    # are the encoders' own
    span = 20
    dq = (obs[:, span:, :2] - obs[:, :-span, :2]) / (span * 1e-3)
    c = np.cumsum(obs[:, :, 2:], axis=1)
    vm = (c[:, span:] - c[:, :-span]) / span
    gap = vm - dq
    out["velocity_error_20ms_rms"] = np.sqrt((gap**2).mean(axis=(0, 1))).tolist()
    out["velocity_error_20ms_over_std"] = (np.sqrt((gap**2).mean(axis=(0, 1))) / scale[2:]).tolist()
    speed = np.abs(dq)
    out["velocity_error_20ms_rms_by_speed"] = {
        f"{lo}-{hi} rad/s": np.sqrt(
            [
                np.mean(gap[..., j][(speed[..., j] >= lo) & (speed[..., j] < hi)] ** 2)
                for j in range(2)
            ]
        ).tolist()
        for lo, hi in ((0, 1), (1, 3), (3, 6), (6, 100))
    }
    out["by_horizon"] = {}
    for k in horizons:
        steps = k * DECIM
        starts = [
            (e, t) for e in range(len(obs)) for t in range(0, obs.shape[1] - steps, STRIDE * DECIM)
        ]
        x0 = np.array([obs[e, t] for e, t in starts])
        meas = np.stack([obs[e, t : t + steps + 1 : DECIM] for e, t in starts])  # [W, k+1, 4]
        amp = np.array(
            [
                np.abs(multiarm.to_world(obs[e, t : t + steps])[:, :2] - np.pi).max()
                for e, t in starts
            ]
        )
        res = {}
        for name, model in (("nominal",) * 2, ("published",) * 2, ("coulomb_arm1",) * 2):
            pred = rollout(effects(model, coulomb), x0, steps)[:, ::DECIM]
            r = (pred[:, 1:] - meas[:, 1:]) / scale  # [W, k, 4]
            mse = float((r**2).mean())
            by_var = (r**2).mean(axis=(0, 1))
            by_step = (r**2).mean(axis=(0, 2))
            thirds = np.array_split(by_step, 4)
            big = amp > np.median(amp)
            res[name] = {
                "mse": mse,
                "share_by_variable": (by_var / by_var.sum()).tolist(),
                "mse_by_quarter_of_window": [float(q.mean()) for q in thirds],
                "mse_large_vs_small_swing_windows": [
                    float((r[big] ** 2).mean()),
                    float((r[~big] ** 2).mean()),
                ],
                "per_window": (r**2).mean(axis=(1, 2)).tolist(),
            }
        out["by_horizon"][str(k)] = {"windows": len(starts), "amplitude": amp.tolist(), **res}
    return out


if __name__ == "__main__":
    result = main()
    atomic_write_json(HERE / "remainder.json", result)
    slim = {k: v for k, v in result.items() if k != "by_horizon"}
    print(json.dumps(slim, indent=1))
    for k, r in result["by_horizon"].items():
        print("k =", k, "windows", r["windows"])
        for m, x in r.items():
            if not isinstance(x, dict):
                continue
            print(
                f"  {m}: mse {x['mse']:.4g} shares {np.round(x['share_by_variable'], 3)} "
                f"quarters {np.round(x['mse_by_quarter_of_window'], 5)} "
                f"large/small {np.round(x['mse_large_vs_small_swing_windows'], 5)}"
            )
    sys.exit(0)
