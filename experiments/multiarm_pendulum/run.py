"""Gap discovery on the real multi-arm pendulum recordings (Kaheman et al. 2022), against the
authors' published identification: `make pendulum` (README.md beside this file).

For the single and the double pendulum:
  (a) start from the authors' parameters without their damping (multiarm_*.xml): discovery
      names the joint friction (viscous damping, Coulomb friction, quadratic drag on every
      hinge) and any inertial mismatch the authors' parameters leave in this simulator;
  (b) start from a nominal model with every mass, centre of mass and inertia 10% off (each
      factor 0.9 or 1.1, a sign pattern no other draw has: `sign_pattern`): discovery names the
      inertial mismatch as well as the friction.
Both starts offer the same candidates: the friction laws on every hinge and mass_scale,
com_scale, inertia_scale on every body (a user's nominal model is never exact, and a free
swing's period shows a 0.1% error in it within seconds).
Discovery fits on the Y_id segments only (decimated, k-step windows: DISCOVER below); every
model is then scored on the held-out Y_vad segments at the recordings' own 1 ms, in one
simulator (hds's, the env's tree engine, MuJoCo's Euler at 1 ms, frames = 1): nominal,
the authors' published fit (the MJCF plus their viscous damping) and hds's corrected model.

Writes outputs/multiarm_pendulum/ (perturbed MJCFs, discovery reports) and this folder's
results.json and heldout_*.png.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

# XLA's C++ log (a notice per persistent-cache hit) is read when jax loads: quiet it first,
# as hds's commands do (hds/__init__.py sets it too, but jax is imported before hds here)
os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from hds.config import compose  # noqa: E402
from hds.data import multiarm  # noqa: E402
from hds.discover import DiscoverConfig, discover, write_report  # noqa: E402
from hds.envs.system import load_spec, make_simulator  # noqa: E402
from hds.utils.io import atomic_write_json  # noqa: E402
from hds.utils.runtime import enable_compilation_cache  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
DATA = ROOT.parent / "shared" / "data" / "multiarm_pendulum"
OUT = ROOT / "outputs" / "multiarm_pendulum"
FILES = {
    "single": "SinglePendulumDataForParameterEstimation.mat",
    "double": "DoublePendulumDataForParameterEstimation.mat",
}
ARMS = {"single": 1, "double": 2}
FRICTION = ["viscous_damping", "coulomb_friction", "quadratic_drag"]
INERTIAL = ["mass_scale", "com_scale", "inertia_scale"]
# Discovery's sampling and windows (item 5: under 60 s on 2 cores). The single pendulum swings
# slowly (period 0.8 s) and its friction shows only over seconds: 10 ms samples, 3 s windows
# every 0.5 s. The double is chaotic at large swings, but its recordings decay to small ones:
# 10 ms samples, 1 s windows every 0.5 s (0.2 s windows showed no friction at all).
# Initial states: discovery's own rule (`initial_state=auto`). Both rigs' velocities were
# de-noised offline and disagree with the encoders' angles beyond white noise
# (`hds.discover.data.velocity_error`: 0.25% of their std on the single, 0.50% and 0.72% on
# the double at 10 ms); where that passes noise_threshold (the double), discovery runs with
# measured and with estimated initial states and keeps the one its own held-out Y_id
# segments support (`choose_initial_states`); Y_vad plays no part in it.
DISCOVER = {
    "single": {"dt": 0.01, "horizon": 300, "stride": 50, "initial_state": "auto"},
    "double": {"dt": 0.01, "horizon": 100, "stride": 50, "initial_state": "auto"},
}
DRAWS = {"single": 5, "double": 5}  # seeded draws of start (b)
KS = (10, 100, 1000)  # k-step horizons, in 1 ms samples
KSTRIDE = 50  # a k-step window starts every 50 samples of a held-out segment
HOLD = 0.1  # rad: a prediction "holds" while its RMS world-angle error stays below this
# ... and, finer, below this: the held-out swings are small (0.16-0.55 rad), so 0.1 rad is
# coarse, and every model holds past the longest k at it
HOLD_FINE = 0.01


def sign_pattern(n: int, draw: int) -> np.ndarray:
    """[n] signs +-1 of draw `draw`: the draw-th of the 2^n sign patterns in the order
    default_rng(0).permutation gives them, so no two draws repeat a pattern (independent
    draws of 3 signs repeat one within 5 draws more often than not)."""
    if not 0 <= draw < 2**n:
        raise ValueError(f"draw {draw} is out of range: {n} factors have 2^{n} sign patterns")
    code = int(np.random.default_rng(0).permutation(2**n)[draw])
    return np.array([1.0 if code >> i & 1 else -1.0 for i in range(n)])


def perturbed_xml(system: str, draw: int) -> tuple[Path, dict]:
    """The nominal model of start (b): every body's mass, COM distance from its joint and
    inertia about its COM times 0.9 or 1.1 (signs: `sign_pattern`, distinct for every draw);
    written as an MJCF."""
    spec = load_spec(f"multiarm_{system}.xml")
    arms = [b for b in spec.bodies if b.name.startswith("arm")]
    signs = sign_pattern(3 * len(arms), draw).reshape(len(arms), 3)
    factors = {}
    for body, sign in zip(arms, signs, strict=True):
        f = 1.0 + 0.1 * sign
        body.mass *= f[0]
        body.ipos = np.asarray(body.ipos) * f[1]  # joints sit at the bodies' origins
        body.inertia = np.asarray(body.inertia) * f[2]
        factors[body.name] = {"mass": f[0], "com": f[1], "inertia": f[2]}
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / f"multiarm_{system}_draw{draw}.xml"
    path.write_text(spec.to_xml())
    return path, factors


def env_config(system: str, xml: str | None = None):
    env = compose([f"env=multiarm_{system}", "data=unused"], "discover").env
    if xml is not None:
        env.xml = str(xml)
    return env


def run_discovery(system: str, env, effects: list[str], label: str):
    c = DISCOVER[system]
    ident, held = multiarm.load(DATA / FILES[system], dt=c["dt"])
    cfg = DiscoverConfig(
        horizon=c["horizon"],
        stride=c["stride"],
        initial_state=c["initial_state"],
        effects=effects,
        max_delay=0,  # zero actions: no delay to find
        slot_buckets=[],  # one compile of the fits (max_effects slots): compiles dominate
        seed=0,
    )
    start, cpu = time.perf_counter(), time.process_time()
    result = discover(ident, env, cfg, validation=held)
    seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
    write_report(result, env, OUT / label)
    named = [
        {
            "effect": e.name,
            "target": e.target,
            "params": {k: float(v) for k, v in e.params.items()},
            "ci95": {k: [float(x) for x in v] for k, v in e.ci95.items()},
        }
        for e in result.missing_effects
    ]
    return result, {
        "named": named,
        "stopped": result.stopped,
        "seconds": seconds,
        # CPU seconds of this process (all its threads): on a shared machine, what the wall
        # time would be on an idle one is between cpu / cores and cpu
        "cpu_seconds": cpu,
        "load_average_1min": os.getloadavg()[0],  # the machine is shared: say how busy it was
        "timing_s": {k: float(v) for k, v in result.timing.items()},
        "heldout_kstep_before": float(result.error("before").normalized),
        "heldout_kstep_after": float(result.error("after").normalized),
        "initial_state": result.initial_state,
        "initial_state_choice": result.initial_state_choice,
        "velocity_error": [float(x) for x in result.data.velocity_error],
        # what measured initial states carry through the windows: part of the noise floor
        "carried_noise_mse": float(result.carried_noise),
        "refused": [
            {"effect": f"{e.name}@{e.target}", "params": dict(e.params), "reason": e.reason}
            for e in result.law_mismatch
        ],
    }


class Scorer:
    """Every model of one system on the held-out segments at 1 ms, in hds's simulator."""

    def __init__(self, system: str):
        self.system, self.arms = system, ARMS[system]
        _, held = multiarm.load(DATA / FILES[system])
        self.held = held.obs  # [E, T+1, 2n] joint coordinates

    def rollout(self, xml: str, effects: list[dict], starts: np.ndarray, steps: int):
        """[steps+1, B, 2n] joint-coordinate predictions from the measured states `starts`."""
        sim, params = make_simulator(
            xml, backend="tree", timestep=1e-3, frames=1, effects=effects, sharpness=50.0
        )
        n = self.arms
        zero = jnp.zeros((sim.n_act,))

        @jax.jit
        def run(x0):
            def one(x):
                state = sim.init(x[:n], x[n:], params)

                def body(s, _):
                    s = sim.step(params, s, zero)
                    return s, sim.observe(params, s)

                _, traj = jax.lax.scan(body, state, None, length=steps)
                return jnp.concatenate([x[None], traj])

            return jax.vmap(one, out_axes=1)(x0)

        return np.asarray(run(jnp.asarray(starts, jnp.float32)), np.float64)

    def angle_error(self, pred, meas):
        """World-angle errors (wrapped), [..., n]."""
        e = multiarm.to_world(pred)[..., : self.arms] - multiarm.to_world(meas)[..., : self.arms]
        return np.arctan2(np.sin(e), np.cos(e))

    def score(self, xml: str, effects: list[dict]) -> dict:
        T = self.held.shape[1] - 1
        whole = self.rollout(xml, effects, self.held[:, 0], T)  # [T+1, E, 2n]
        err = self.angle_error(whole, np.swapaxes(self.held, 0, 1))
        starts = [(e, t) for e in range(len(self.held)) for t in range(0, T - max(KS), KSTRIDE)]
        x0 = np.array([self.held[e, t] for e, t in starts])
        traj = self.rollout(xml, effects, x0, max(KS))  # [K+1, W, 2n]
        idx = np.array([t for _, t in starts])
        ep = np.array([e for e, _ in starts])
        meas = np.stack([self.held[ep, idx + j] for j in range(max(KS) + 1)])
        kerr = self.angle_error(traj, meas)  # [K+1, W, n]
        rms_k = np.sqrt((kerr**2).mean(axis=(1, 2)))  # per horizon, over windows and arms
        holds = np.flatnonzero(rms_k > HOLD)
        fine = np.flatnonzero(rms_k > HOLD_FINE)
        return {
            "whole_rms_rad": float(np.sqrt((err**2).mean())),
            "whole_rms_per_segment": np.sqrt((err**2).mean(axis=(0, 2))).tolist(),
            "kstep_rms_rad": {str(k): float(rms_k[k]) for k in KS},
            "holds_ms": float(holds[0]) if len(holds) else float(max(KS)),
            "holds_fine_ms": float(fine[0]) if len(fine) else float(max(KS)),
            "trajectory": whole[:, 0],  # segment 0, for the figure
        }


def figure(system: str, scorer: Scorer, curves: dict, path: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seconds = 3.0 if system == "single" else 1.5
    n = int(seconds / 1e-3)
    t = np.arange(n + 1) * 1e-3
    meas = multiarm.to_world(scorer.held[0])
    fig, axes = plt.subplots(scorer.arms, 1, figsize=(8, 2.6 * scorer.arms), squeeze=False)
    for i, ax in enumerate(axes[:, 0]):
        ax.plot(t, meas[: n + 1, i], "k", lw=2.2, label="measured (held-out Y_vad[0])")
        for label, traj in curves.items():
            ax.plot(t, multiarm.to_world(traj)[: n + 1, i], lw=1.1, label=label)
        ax.set_ylabel(f"phi{i + 1} (rad, world)")
    axes[-1, 0].set_xlabel("s from the segment's first sample")
    axes[0, 0].legend(fontsize=7, loc="upper right")
    axes[0, 0].set_title(f"{system} pendulum: held-out segment 0 from its first sample")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def tables(results: dict) -> str:
    """The README's tables (markdown) from results.json: held-out errors in mrad, discoveries."""
    lines = []
    for system in ("single", "double"):
        if system not in results:
            continue
        out = results[system]
        rows = dict(out["rows"])
        for key, name in (("nominal", "nominal (b)"), ("corrected", "hds corrected (b)")):
            draws = [d[key] for d in out["discoveries"]["b"]]
            for field in ("whole_rms_rad", "holds_ms", "holds_fine_ms"):
                values = np.array([d.get(field, np.nan) for d in draws])
                rows.setdefault(name, {})[field] = values
            for k in KS:
                values = np.array([d["kstep_rms_rad"][str(k)] for d in draws])
                rows[name].setdefault("kstep_rms_rad", {})[str(k)] = values

        def cell(v, scale=1e3):
            v = np.atleast_1d(np.asarray(v, dtype=np.float64)) * scale
            if len(v) == 1:
                return f"{v[0]:.3g}"
            return f"{v.mean():.3g} [{v.min():.3g}, {v.max():.3g}]"

        lines += [
            f"\n{system} pendulum, held-out Y_vad (RMS world-angle error, mrad; (b): mean "
            f"[min, max] over {len(out['discoveries']['b'])} draws)\n",
            "| model | whole segment | k = 10 | k = 100 | k = 1000 | holds (ms, RMS < "
            f"{results['hold_rad']:g} rad) | holds (ms, RMS < {HOLD_FINE:g} rad) |",
            "| --- | --- | --- | --- | --- | --- | --- |",
        ]
        for name, r in rows.items():
            ks = [cell(r["kstep_rms_rad"][str(k)]) for k in KS]
            fine = r.get("holds_fine_ms")
            lines.append(
                f"| {name} | {cell(r['whole_rms_rad'])} | {' | '.join(ks)} | "
                f"{holds(r['holds_ms'])} | {'-' if fine is None else holds(fine)} |"
            )
        lines += [
            "",
            "| start | named (95% CI) | discovery s, wall / CPU (1-min load average) |",
            "| --- | --- | --- |",
        ]
        for label, infos in (("a", [out["discoveries"]["a"]]), ("b", out["discoveries"]["b"])):
            for i, info in enumerate(infos):
                named = (
                    "; ".join(
                        f"{e['effect']}@{e['target']} "
                        + ", ".join(
                            f"{p} = {v:.4g} [{e['ci95'][p][0]:.4g}, {e['ci95'][p][1]:.4g}]"
                            for p, v in e["params"].items()
                        )
                        for e in info["named"]
                    )
                    or "nothing"
                )
                tag = label if label == "a" else f"b, draw {i} {_factors(info['factors'])}"
                load = info.get("load_average_1min", float("nan"))
                cpu = info.get("cpu_seconds", float("nan"))
                lines.append(
                    f"| {tag} | {named} | {info['seconds']:.0f} / {cpu:.0f} ({load:.1f}) |"
                )
    return "\n".join(lines)


def choices(results: dict) -> str:
    """Per discovery: the velocities' error, the noise the measured states carry through the
    windows (`carried_noise`), both starts' held-out k-step errors where both ran, the start
    chosen, and what was refused and why (markdown)."""
    lines = [
        "\n| rig, start | velocity error (share of std) | carried noise (MSE per residual) | "
        "held-out k-step, measured / estimated | chosen | refused (rule's numbers) |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for system in ("single", "double"):
        if system not in results:
            continue
        runs = results[system]["discoveries"]
        for tag, info in [("a", runs["a"])] + [(f"b{i}", d) for i, d in enumerate(runs["b"])]:
            error = info.get("initial_state_choice", {}).get("heldout_error", {})
            held = (
                f"{error['measured']:.4f} / {error['estimated']:.4f}"
                if error
                else f"{info['heldout_kstep_after']:.4f} / not run"
            )
            velocity = ", ".join(f"{v:.2%}" for v in info.get("velocity_error", []))
            refused = "; ".join(
                f"{r['effect']}: {r['reason']}" for r in info.get("refused", []) if r["reason"]
            )
            lines.append(
                f"| {system} {tag} | {velocity} | {info.get('carried_noise_mse', 0.0):.3g} | "
                f"{held} | {info['initial_state']} | {refused or '-'} |"
            )
    return "\n".join(lines)


def diagnostics() -> str:
    """What the recordings are (numpy only, seconds): each segment's swing amplitude at its start
    and end, and, for the single pendulum, the viscous k1 that minimises each segment's
    whole-segment error in the authors' equation integrated as the simulator does (semi-implicit
    Euler, 1 ms) with their other parameters."""
    lines = ["\n| segment | amplitude at start, end (rad from hanging, per arm) | end / start |"]
    lines.append("| --- | --- | --- |")
    for system in ("single", "double"):
        ident, held = multiarm.load(DATA / FILES[system])
        for name, d in (("Y_id", ident), ("Y_vad", held)):
            w = multiarm.to_world(d.obs)[..., : ARMS[system]] - np.pi
            first, last = np.abs(w[:, :800]).max(axis=1), np.abs(w[:, -800:]).max(axis=1)
            for e in range(d.n_episodes):
                amp = ", ".join(f"{a:.2f} -> {b:.2f}" for a, b in zip(first[e], last[e]))
                ratio = ", ".join(f"{b / a:.3f}" for a, b in zip(first[e], last[e]))
                lines.append(f"| {system} {name}[{e}] | {amp} | {ratio} |")
    p = multiarm.PUBLISHED[1]
    J, G = p["m1"] * p["a1"] ** 2 + p["I1"], p["m1"] * p["g"] * p["a1"]
    ks = np.arange(1.2, 3.01, 0.1) * 1e-4
    lines += ["", "| single segment | k1 minimising its whole-segment error (N m s/rad) |"]
    lines.append("| --- | --- |")
    ident, held = multiarm.load(DATA / FILES["single"])
    for name, d in (("Y_id", ident), ("Y_vad", held)):
        th = np.repeat(d.obs[:, 0, :1], len(ks), 1)
        w = np.repeat(d.obs[:, 0, 1:], len(ks), 1)
        err = np.zeros_like(th)
        for t in range(1, d.horizon + 1):
            w = w + 1e-3 * (G * np.sin(th) - ks * w) / J
            th = th + 1e-3 * w
            err += (th - d.obs[:, t, :1]) ** 2
        for e in range(d.n_episodes):
            best = ks[np.argmin(err[e])]
            edge = " (the grid's edge)" if best in (ks[0], ks[-1]) else ""
            lines.append(f"| {name}[{e}] | {best:.2e}{edge} |")
    return "\n".join(lines) + "\n" + swing_losses()


def half_swings(segments, offset: float):
    """Per half swing of the single pendulum's segments (turning point to turning point):
    amplitude (rad from hanging, the mean of its two turning points; `offset` the hanging
    angle's offset), half period (s), the energy lost (J, from the authors' J and m g a), the
    integrals of qd^2, |qd|, |qd|^3 dt over it (the loss of viscous damping, dry friction and
    quadratic drag per coefficient) and its direction (the sign of qd)."""
    p = multiarm.PUBLISHED[1]
    J, G = p["m1"] * p["a1"] ** 2 + p["I1"], p["m1"] * p["g"] * p["a1"]
    rows = []
    for th, w in segments:
        energy = 0.5 * J * w**2 + G * np.cos(th - offset)
        turns = np.flatnonzero(np.sign(w[1:]) != np.sign(w[:-1]))
        keep = [turns[0]]
        for i in turns[1:]:  # a sign change of the de-noised velocity within 0.15 s is noise
            if i - keep[-1] > 150:
                keep.append(i)
        for a, b in zip(keep[:-1], keep[1:]):
            v = np.abs(w[a : b + 1])
            amplitude = 0.5 * (abs(np.pi + offset - th[a]) + abs(np.pi + offset - th[b]))
            integrals = [(v**k).sum() * multiarm.SAMPLE_DT for k in (2, 1, 3)]
            period = (b - a) * multiarm.SAMPLE_DT
            direction = np.sign(w[(a + b) // 2])
            rows.append([amplitude, period, energy[a] - energy[b], *integrals, direction])
    return np.array(rows), J, G


def swing_losses() -> str:
    """Which friction law the single pendulum's recordings support, from energy alone (numpy,
    no simulator, no phase): the loss per half swing regressed on each law's integral, on the
    identification segments only; the amplitude's fall per half swing by amplitude; the
    half period against the frictionless model's (the authors' J / (m g a)). The hanging
    angle's offset is where the two directions' losses agree."""
    from scipy.special import ellipk

    raw = multiarm.read_mat(DATA / FILES["single"])
    offsets = np.linspace(-0.004, 0.004, 81)
    every = raw["Y_id"] + raw["Y_vad"]

    def alternation(offset):
        rows, _, _ = half_swings(every, offset)
        k, up = rows[:, 2] / rows[:, 3], rows[:, 6] > 0
        return abs(k[up].mean() - k[~up].mean())

    offset = float(min(offsets, key=alternation))
    ident, J, G = half_swings(raw["Y_id"], offset)
    lines = [
        f"\nSingle pendulum, energy per half swing (hanging offset {offset * 1e3:.1f} mrad): "
        f"the loss on the {len(ident)} identification half swings regressed on each law",
        "",
        "| laws | viscous (N m s/rad) | Coulomb (N m) | quadratic (N m s^2/rad^2) | "
        "relative residual |",
        "| --- | --- | --- | --- | --- |",
    ]
    for name, cols in (
        ("viscous", [0]),
        ("viscous + Coulomb", [0, 1]),
        ("Coulomb + quadratic", [1, 2]),
        ("all three", [0, 1, 2]),
    ):
        X = ident[:, [3 + c for c in cols]]
        coef, *_ = np.linalg.lstsq(X, ident[:, 2], rcond=None)
        value = ["-"] * 3
        for c, v in zip(cols, coef):
            value[c] = f"{v:.3g}"
        res = ident[:, 2] - X @ coef
        rel = np.sqrt(np.mean(res**2) / np.mean(ident[:, 2] ** 2))
        lines.append(f"| {name} | {' | '.join(value)} | {rel:.3f} |")
    rows = np.concatenate([half_swings([seg], offset)[0] for seg in every])
    amp, fall = rows[:, 0], []
    for seg in every:  # the fall between consecutive turning points, within a segment
        r = half_swings([seg], offset)[0]
        fall += [np.nan] + list(-np.diff(r[:, 0]))
    fall = np.array(fall)
    lines += [
        "",
        "| amplitude (rad) | half swings | fall per half swing (mrad) | fall / amplitude | "
        "half period measured / model |",
        "| --- | --- | --- | --- | --- |",
    ]
    model = 2 * np.sqrt(J / G) * ellipk(np.sin(rows[:, 0] / 2) ** 2)
    for lo in np.arange(0.2, 1.7, 0.2):
        m = (amp >= lo) & (amp < lo + 0.2) & np.isfinite(fall)
        if m.any():
            ratio = (rows[m, 1] / model[m]).mean()
            lines.append(
                f"| {lo:.1f}-{lo + 0.2:.1f} | {m.sum()} | {fall[m].mean() * 1e3:.2f} | "
                f"{(fall[m] / amp[m]).mean():.4f} | {ratio:.4f} |"
            )
    return "\n".join(lines)


def holds(ms) -> str:
    """How long the k-step predictions hold; '> 1000' where they never crossed within max(KS)."""
    ms = np.atleast_1d(np.asarray(ms, dtype=np.float64))
    if np.isnan(ms).all():  # not measured (a results.json from before the column)
        return "-"
    text = [f"> {max(KS)}" if m >= max(KS) else f"{m:.0f}" for m in ms]
    return text[0] if len(text) == 1 else ", ".join(text)


def _factors(factors: dict) -> str:
    return (
        "("
        + ", ".join(
            f"{b}: m {f['mass']:g} c {f['com']:g} I {f['inertia']:g}" for b, f in factors.items()
        )
        + ")"
    )


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--systems", nargs="+", default=["single", "double"])
    parser.add_argument("--draws", type=int, default=None, help="draws of (b); default DRAWS")
    parser.add_argument("--tables", action="store_true", help="print results.json's tables")
    args = parser.parse_args(argv)
    if args.tables:
        results = json.loads((HERE / "results.json").read_text())
        print(tables(results))
        print(choices(results))
        print(diagnostics())
        return
    enable_compilation_cache()  # as `python -m hds.discover` does: a rerun skips the compiles
    results = {"date": "2026-11-28", "discover": DISCOVER, "ks": KS, "hold_rad": HOLD}
    for system in args.systems:
        arms = ARMS[system]
        xml = f"multiarm_{system}.xml"
        scorer = Scorer(system)
        rows, curves = {}, {}
        published = multiarm.published_effects(arms)
        for label, model_xml, effects in (
            ("nominal (a): published, no damping", xml, []),
            ("published fit", xml, published),
        ):
            rows[label] = scorer.score(model_xml, effects)
            curves[label] = rows[label].pop("trajectory")
        out = {"rows": rows, "discoveries": {}}
        # (a): from the authors' parameters without damping
        result, info = run_discovery(system, env_config(system), FRICTION + INERTIAL, f"{system}_a")
        label = "hds corrected (a)"
        rows[label] = scorer.score(xml, result.corrected_effects)
        curves[label] = rows[label].pop("trajectory")
        out["discoveries"]["a"] = info
        # (b): inertial mismatch and friction from a perturbed nominal, several draws
        out["discoveries"]["b"] = []
        for draw in range(DRAWS[system] if args.draws is None else args.draws):
            pxml, factors = perturbed_xml(system, draw)
            result, info = run_discovery(
                system, env_config(system, pxml), FRICTION + INERTIAL, f"{system}_b{draw}"
            )
            info["factors"] = {b: {k: float(v) for k, v in f.items()} for b, f in factors.items()}
            info["nominal"] = scorer.score(str(pxml), [])
            info["corrected"] = scorer.score(str(pxml), result.corrected_effects)
            trajectories = (info["nominal"].pop("trajectory"), info["corrected"].pop("trajectory"))
            if draw == 0:
                curves["nominal (b), draw 0"], curves["hds corrected (b), draw 0"] = trajectories
            out["discoveries"]["b"].append(info)
            print(system, "draw", draw, json.dumps(info["named"]), f"{info['seconds']:.1f} s")
        figure(system, scorer, curves, HERE / f"heldout_{system}.png")
        results[system] = out
        print(system, json.dumps(rows, indent=1))
        print(system, "(a)", json.dumps(out["discoveries"]["a"]))
    path = HERE / "results.json"  # systems run apart (--systems) merge into one file
    if path.is_file() and set(args.systems) != set(ARMS):
        results = json.loads(path.read_text()) | results
    atomic_write_json(path, results)
    print(tables(results))
    print(choices(results))
    print(diagnostics())


if __name__ == "__main__":
    main()
