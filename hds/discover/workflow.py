"""The whole workflow as a function: compare, locate, explain, name (step 4 lives here: it
turns the selection into named effects with units, confidence intervals and shares)."""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from hds.data.budget import DISCOVERY, Progress, check
from hds.data.format import Dataset
from hds.discover.compare import Errors, Residuals, compare
from hds.discover.config import DiscoverConfig
from hds.discover.data import Data, prepare
from hds.discover.explain import (
    Selection,
    State,
    by_contribution,
    correlations,
    delay_range,
    forward_selection,
    intervals,
    judge_path,
)
from hds.discover.fit import Engine, confidence_intervals, get_engine
from hds.discover.identify import Identifiability, identifiability
from hds.discover.locate import Location, locate
from hds.discover.terms import Reading, Term, compensations, fit_terms, with_terms
from hds.effects.base import ACTUATOR
from hds.effects.force_terms import FEATURE
from hds.effects.library import effect_type

log = logging.getLogger("hds")


@dataclass
class NamedEffect:
    name: str  # effect of the library
    target: str  # joint, actuator, body or observation
    params: dict[str, float]
    units: dict[str, str]
    ci95: dict[str, list[float]]
    explained_fraction: float  # share of the held-out k-step error (MSE) it removed
    at_joint: dict[str, float] = field(default_factory=dict)  # control-unit values x gear
    # refused as law mismatch: which rule refused it, with the numbers it compared
    reason: str = ""

    @property
    def physical_name(self) -> str:
        return effect_type(self.name).physical_name

    def to_json(self) -> dict:
        return {
            "name": self.name,
            "target": self.target,
            "params": self.params,
            "units": self.units,
            "ci95": self.ci95,
            "explained_fraction": self.explained_fraction,
            "physical_name": self.physical_name,
            "at_joint": self.at_joint,
            "kind": effect_type(self.name).target_kind,
            **({"reason": self.reason} if self.reason else {}),
        }

    def fitted(self, units: bool = False) -> str:
        """Each parameter's value (with its unit) and 95% interval: "force = 20.4 [18.7, 22.1]"."""
        return ", ".join(
            f"{p} = {v:.4g}"
            + (f" {self.units.get(p, '')}" if units else "")
            + (f" [{self.ci95[p][0]:.4g}, {self.ci95[p][1]:.4g}]" if p in self.ci95 else "")
            for p, v in self.params.items()
        )

    def as_effect(self) -> dict:
        """The effect as an `env.effects` entry."""
        return {"name": self.name, "target": self.target, "params": dict(self.params)}


@dataclass
class Discovery:
    """What gap discovery found in one dataset: the effects it named (`missing_effects`), the
    errors before and after adding them, the candidates it fitted and why it stopped."""

    missing_effects: list[NamedEffect]
    before: dict[str, tuple[Residuals, Errors]]  # per set (identification, heldout, validation)
    after: dict[str, tuple[Residuals, Errors]]
    candidates: list[dict]
    unexplained_fraction: float
    location: Location
    selection: Selection
    stopped: str
    data: Data
    engine: Engine
    env_effects: list[dict]  # what the simulator already modelled
    timing: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    tentative: list[NamedEffect] = field(default_factory=list)  # compensations, not named
    remainder: Location | None = None  # locate on what the named effects leave
    structured_unexplained: float = 0.0  # the unexplained share that features explain
    initial_state: str = "measured"  # how the fits started each window
    # where the velocities' smooth error left the choice to the held-out episodes
    # (`choose_initial_states`): the error, both modes' held-out errors, the mode chosen
    initial_state_choice: dict = field(default_factory=dict)
    # the mean squared normalized residual the measured initial states' error carries
    # through the identification windows, part of the noise floor (`Engine.carried_noise`)
    carried_noise: float = 0.0
    final: State | None = None  # the corrected model (theta, delays) of the named effects
    backend: str = ""  # the physics backend the fits ran on
    no_gap: bool = False  # the simulator already predicted the data (to min_improvement)
    cfg: DiscoverConfig | None = None
    identifiability: list[Identifiability] = field(default_factory=list)  # before fitting
    correlations: list[dict] = field(default_factory=list)  # between the named effects' params
    law_mismatch: list[NamedEffect] = field(default_factory=list)  # see `discover`
    terms: list[Term] = field(default_factory=list)  # sparse force terms beyond the library
    # how the term fit read each hinge's angle: unwrapped (q offered) or periodic
    angle_readings: list[Reading] = field(default_factory=list)
    # per set, the corrected simulator's (named effects and terms) residuals and errors; empty
    # when no term is found
    after_terms: dict[str, tuple[Residuals, Errors]] = field(default_factory=dict)

    def errors_on(self, dataset: Dataset, set_name: str = "heldout") -> tuple[Errors, Errors]:
        """Errors before and after on another dataset with this one's layout and split, e.g.
        a noise-free copy of noisy data (what the corrected model gains against the truth)."""
        model, cfg = self.engine.model, self.cfg
        data = prepare(
            dataset, model.sim, model.pad, cfg.horizon, cfg.stride, cfg.heldout_fraction, cfg.seed
        )
        no_delay = np.zeros(len(model.sim.action_names), np.int32)
        before = compare(self.engine, data, model.nominal, no_delay)[set_name][1]
        after = compare(self.engine, data, self.final.theta, self.final.delay)[set_name][1]
        return before, after

    @property
    def corrected_effects(self) -> list[dict]:
        """The env's effects, the named ones and the terms beyond the library."""
        return with_terms(
            self.env_effects + [e.as_effect() for e in self.missing_effects], self.terms
        )

    def error(self, which: str, set_name: str = "heldout") -> Errors:
        return (self.before if which == "before" else self.after)[set_name][1]

    @property
    def remainder_fraction(self) -> float:
        """The share of the simulator's held-out k-step error (MSE) that the corrected model
        (`corrected_effects`: the named effects and the force terms beyond the library)
        still leaves; 0 where there was no gap. `unexplained_fraction` is what the named
        effects alone leave, before any term."""
        if self.no_gap:
            return 0.0
        before = self.error("before").normalized ** 2
        after = (self.after_terms or self.after)["heldout"][1].normalized ** 2
        return float(after / before) if before > 0 else 0.0

    @property
    def noise_fraction(self) -> float:
        """The share of the simulator's held-out k-step error (MSE) that the measurement
        noise alone accounts for (the estimated noise floor), at most the remainder: the
        rest of `remainder_fraction` is what no model of hds's explains."""
        before = self.error("before").normalized ** 2
        floor = self.noise_floor**2
        return float(min(floor / before, self.remainder_fraction)) if before > 0 else 0.0

    @property
    def noise_floor(self) -> float:
        """The normalized RMSE measurement noise alone leaves (estimated from the data)."""
        relative = self.data.noise / np.asarray(self.data.scale, dtype=np.float64)
        return float(np.sqrt(np.mean(relative**2)))

    def to_json(self) -> dict:
        names = list(self.data.obs_names)
        out = {
            "missing_effects": [e.to_json() for e in self.missing_effects],
            "error_before": self.error("before").to_json(names),
            "error_after": self.error("after").to_json(names),
            "candidates": self.candidates,
            "unexplained_fraction": self.unexplained_fraction,
            "remainder_fraction": self.remainder_fraction,
            "noise_fraction": self.noise_fraction,
            "gap_found": not self.no_gap,
            "structured_unexplained_fraction": self.structured_unexplained,
            "tentative_effects": [e.to_json() for e in self.tentative],
            "law_mismatch": [e.to_json() for e in self.law_mismatch],
            "dropped_proxies": [c.key for c in self.selection.dropped],
            "correlations": self.correlations,
            "terms_beyond_the_library": [t.to_json() for t in self.terms],
            "angle_readings": [r.to_json() for r in self.angle_readings],
            "errors_with_terms": {
                s: errors.to_json(names) for s, (_, errors) in self.after_terms.items()
            },
            "identifiability": [r.to_json() for r in self.identifiability],
            "noise_std": [float(x) for x in self.data.noise],
            "noise_floor_nrmse": self.noise_floor,
            "initial_state": self.initial_state,
            "initial_state_choice": self.initial_state_choice,
            "carried_noise_mse": self.carried_noise,
            "velocity_error": [float(x) for x in self.data.velocity_error],
            "backend": self.backend,
            "stopped": self.stopped,
            "horizon_steps": self.data.horizon,
            "dt": self.data.dt,
            "episodes": {k: [int(e) for e in v[1]] for k, v in self.data.source.items()},
            "errors": {
                s: {
                    "before": self.before[s][1].to_json(names),
                    "after": self.after[s][1].to_json(names),
                }
                for s in self.before
            },
            "locate": self.location.table[:10],
            "locate_after": self.remainder.table[:10] if self.remainder else [],
            "corrected_effects": self.corrected_effects,
            "warnings": self.warnings,
            "timing_s": self.timing,
        }
        return out


Result = Discovery  # its name until 2026-11-27 (`from hds.discover import Result` still works)


def discover(
    dataset: Dataset,
    env_cfg,
    cfg: DiscoverConfig | None = None,
    validation: Dataset | None = None,
    *,
    path: list[str] | None = None,
) -> Discovery:
    """Find which effects of the library the simulator of `env_cfg` misses on `dataset`.

    Episodes are split into identification and held-out sets; `validation` (optional) is a
    further dataset whose errors are reported before and after, never fitted. `path`: keys
    of candidates, in order (another discovery's `selection.path`), refitted and judged
    instead of searched for (`judge_path`: the initial-state choice's second start)."""
    cfg = cfg or DiscoverConfig()
    cfg.check()
    # refused past discover.max_steps before anything compiles (every caller: the commands,
    # the loop, the corrected simulator, the API); long work shows its stages as they end
    steps = sum(d.n_episodes * d.horizon for d in (dataset, validation) if d is not None)
    check(DISCOVERY, steps, cfg.max_steps, "the data" + (" and validation" if validation else ""))
    progress = Progress(DISCOVERY, steps, log)
    timing = {}
    start = time.perf_counter()
    backend = fit_backend(env_cfg, cfg.backend)
    env_cfg = with_backend(env_cfg, backend)
    engine = get_engine(env_cfg, dataset.dt, cfg.effects, cfg.max_delay, cfg.warmup, cfg.horizon)
    model = engine.model
    data = prepare(
        dataset,
        model.sim,
        model.pad,
        cfg.horizon,
        cfg.stride,
        cfg.heldout_fraction,
        cfg.seed,
        validation,
    )
    relative_noise = data.noise / np.asarray(data.scale, dtype=np.float64)
    estimate = cfg.initial_state == "estimated" or (
        cfg.initial_state == "auto" and float(np.median(relative_noise)) > cfg.noise_threshold
    )
    smooth = not estimate and smooth_velocity_error(data, cfg)
    if cfg.initial_state == "auto" and smooth:
        return choose_initial_states(dataset, env_cfg, cfg, validation, data.velocity_error)
    nominal, no_delay = model.nominal, np.zeros(len(model.sim.action_names), np.int32)
    before = compare(engine, data, nominal, no_delay)
    timing["compare"] = time.perf_counter() - start
    progress("the simulator compared with the data")

    t0 = time.perf_counter()
    checks = identifiability(dataset, env_cfg, cfg.min_motion, cfg.effects)
    banned = {r.key for r in checks if not r.identifiable}
    timing["identifiability"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    location = locate(data, model.sim, before["identification"][0], cfg.bins)
    timing["locate"] = time.perf_counter() - t0
    progress("the gap located")

    t0 = time.perf_counter()
    log.info(
        "initial states %s (estimated noise: %s of each signal's std)",
        "estimated" if estimate else "measured",
        np.round(relative_noise, 4).tolist(),
    )
    floor = float(np.sqrt(np.mean(relative_noise**2)))
    ident = data.arrays("identification")
    carried = 0.0
    if smooth:
        # measured states whose velocities carry a smooth error: a correct model would still
        # leave what that error (and the states' white noise) carries through each window,
        # and the error of every compared velocity sample, which the white-noise floor
        # leaves out
        spread = relative_noise.copy()
        nq = len(data.velocity_error)
        spread[nq:] = np.sqrt(spread[nq:] ** 2 + data.velocity_error**2)
        carried = engine.carried_noise(nominal, no_delay, ident, spread)
        carried += float(np.sum(data.velocity_error**2)) / len(spread)
        log.info(
            "measured initial states carry %.3g (mean squared normalized residual) through "
            "the windows, against %.3g of white noise in the samples",
            carried,
            floor**2,
        )
    if path is None:
        selection = forward_selection(
            engine, ident, data.arrays("heldout"), cfg, estimate, floor, banned, progress, carried
        )
    else:
        by_key = {c.key: c for c in model.candidates}
        chosen = [by_key[k] for k in path]
        selection = judge_path(
            engine, ident, data.arrays("heldout"), cfg, chosen, estimate, floor, carried
        )

    # What the selected effects leave: if a feature still explains much of it, the gap has a
    # structure no effect of the library has, and an effect that explains less than that
    # structured remainder is a compensation for it, not a finding: it stays tentative.
    def judged(selection):
        full = compare(engine, data, selection.final.theta, selection.final.delay)
        remainder = locate(data, model.sim, full["identification"][0], cfg.bins)
        shares = explained_shares(selection)
        structured = shares[-1] * structure(remainder)
        return full, remainder, shares, structured, _cut(shares, structured)

    full, remainder, shares, structured, mismatch = judged(selection)
    if any(s >= structured for s in shares[mismatch + 1 : -1]):
        # an effect below the structured remainder before one above it: the chain in the
        # order of what each adds beside the others, so the cut takes only the weak ones
        selection = by_contribution(
            engine, ident, data.arrays("heldout"), cfg, selection, estimate, floor, carried
        )
        full, remainder, shares, structured, mismatch = judged(selection)
    named_count = min(mismatch, _separable_count(model, selection.final, selection.shown))
    final = selection.states[named_count]
    after = (
        full if named_count == len(shares) - 1 else compare(engine, data, final.theta, final.delay)
    )
    if named_count < len(shares) - 1:
        remainder = locate(data, model.sim, after["identification"][0], cfg.bins)
    timing["explain"] = time.perf_counter() - t0

    steps = delay_range(engine, final, ident, floor)
    effects = name_effects(model, selection.states[: named_count + 1], shares, steps)
    rest = name_effects(model, selection.states, shares)
    # below the structured remainder: the named laws' own mismatch (MuJoCo's friction and
    # filter are not the library's laws), not a finding; otherwise a compensation for an
    # effect the data cannot separate from a named one
    if mismatch > 0:
        tentative, law_mismatch = rest[named_count:mismatch], rest[max(named_count, mismatch) :]
        for e in law_mismatch:
            e.reason = (
                f"it, or an effect selected before it, removed less than the {structured:.1%} "
                "of the held-out error that the structure of the named effects' residual holds"
            )
    else:  # no law named: what it leaves is structure outside the library
        tentative, law_mismatch = rest[named_count:], []
    # no gap at all (the simulator already predicts the held-out data to min_improvement):
    # nothing is left to explain
    no_gap = selection.states[0].heldout_error < cfg.min_improvement
    unexplained = 0.0 if no_gap else float(sum(shares[named_count:]))
    candidates = [row for rows in selection.rounds for row in rows]
    candidates.sort(key=lambda r: (r["round"], r["heldout_error"]))
    result = Discovery(
        effects,
        before,
        after,
        candidates,
        unexplained,
        location,
        selection,
        selection.stopped,
        data,
        engine,
        [_effect_dict(e) for e in model.env_effects],
        timing,
    )
    refused = [
        dataclasses.replace(
            name_effects(model, [m], [0.0] * (len(m.selected) - 1) + [share])[-1],
            reason=m.refused_because,
        )
        for m, share in refused_shares(selection)
    ]
    result.tentative, result.law_mismatch = tentative, law_mismatch + refused
    result.identifiability = checks
    # the library leaves much: look beyond it, unless what it leaves is an effect the data
    # cannot identify (a cart that friction holds still), which terms would only compensate
    if unexplained > cfg.unexplained_warning and not selection.unidentified:
        t0 = time.perf_counter()
        result.terms, result.angle_readings = fit_terms(
            env_cfg, data, after["identification"][0], after["heldout"][0], cfg.stop_margin
        )
        if result.terms:  # the corrected simulator, terms included, on the same windows
            result.after_terms = corrected_errors(env_cfg, result.corrected_effects, data, cfg)
        timing["terms"] = time.perf_counter() - t0
    if effects and not no_gap and not selection.unidentified:
        t0 = time.perf_counter()
        if spring_rival(env_cfg, data, before, result, cfg):
            # the named effects only compensated a spring: nothing of the library is named
            final, remainder, unexplained = selection.states[0], location, 1.0
            result.after, result.unexplained_fraction = before, 1.0
        timing["spring_rival"] = time.perf_counter() - t0
    result.correlations = correlations(final) if final.selected else []
    result.remainder = remainder
    result.structured_unexplained = float(unexplained * structure(remainder))
    result.initial_state = "estimated" if estimate else "measured"
    result.carried_noise = carried
    result.final, result.cfg, result.backend = final, cfg, backend
    result.no_gap = no_gap
    result.warnings = warnings(result, cfg)
    timing["total"] = time.perf_counter() - start
    progress("done")
    return result


def smooth_velocity_error(data: Data, cfg: DiscoverConfig) -> bool:
    """Whether some recorded velocity disagrees with its coordinate's recorded change by more
    than noise_threshold of its std beyond white noise (`hds.discover.data.velocity_error`):
    an error the white-noise estimate cannot see, which measured initial states carry into
    every window."""
    return bool(data.velocity_error.size) and float(data.velocity_error.max()) > (
        cfg.noise_threshold
    )


def choose_initial_states(
    dataset: Dataset, env_cfg, cfg: DiscoverConfig, validation, velocity_error
) -> Discovery:
    """Discovery with measured and with estimated initial states, the one its own held-out
    episodes support. A smooth velocity error puts a measured state's error into every window,
    which the fits then read as the laws' mismatch; estimated states take it out but are free
    to absorb part of what the effects do within a window (a phase, an amplitude). Which costs
    more depends on the windows and the effects, not on the record alone, so the held-out
    episodes decide, as they decide every effect: each model predicts them from their measured
    states (as it will be used), and the estimated states are kept only where they lower that
    error by the selection margin (stop_margin); the measured start is the cheaper default.

    One search, two judgements: the measured start searches (`forward_selection`); the
    estimated start refits the effects that search selected, in its order, and judges them
    by the same rules (`judge_path`) instead of searching again. Both starts are compared on
    the same effects, so what decides is the initial states alone, and the estimated start
    costs a few batched fits instead of a search's rounds."""
    measured = discover(
        dataset, env_cfg, dataclasses.replace(cfg, initial_state="measured"), validation
    )
    path = [c.key for c in measured.selection.path]
    estimated = discover(
        dataset, env_cfg, dataclasses.replace(cfg, initial_state="estimated"), validation, path=path
    )
    runs = {"measured": measured, "estimated": estimated}
    error = {mode: float(r.error("after").normalized) for mode, r in runs.items()}
    better = error["estimated"] < (1.0 - cfg.stop_margin) * error["measured"]
    result = runs["estimated" if better else "measured"]
    result.initial_state_choice = {
        "heldout_error": error,
        "chosen": result.initial_state,
        "selected_with_measured_states": path,
    }
    if result is estimated:  # its effects were searched for with measured states
        result.candidates = measured.candidates
    log.info(
        "initial states %s: the velocities' smooth error is %s of their std; held-out k-step "
        "error with measured states %.4g, with estimated %.4g",
        result.initial_state,
        np.round(velocity_error, 4).tolist(),
        error["measured"],
        error["estimated"],
    )
    for mode, r in runs.items():
        result.timing[f"initial_state_{mode}"] = r.timing.get("total", 0.0)
    result.timing["total"] = sum(r.timing.get("total", 0.0) for r in runs.values())
    return result


SPRING_SHARE = 0.5  # a term in a joint's own position explaining this share of its force


def spring_rival(env_cfg, data: Data, before, result: Discovery, cfg: DiscoverConfig) -> bool:
    """Whether the named effects only compensate a spring, and if so make them tentative and
    the terms fitted on the whole gap the corrected model's. No effect of the library is a
    force in a joint's own position; a hinge spring within a turn is fitted as hinge
    friction (87% of the error) or a sensor bias of half a turn, leaving too little for the
    terms to be fitted at all. The rival: the sparse terms of the simulator's own gap, before
    any effect. It wins where its first term on some joint is in that joint's position q and
    explains most (SPRING_SHARE) of the joint's missing force, no term of a named effect's
    own law is among its terms (that effect is not a compensation), and the simulator with
    the terms alone predicts the held-out episodes better than the corrected model by the
    selection margin (stop_margin)."""
    terms, angles = fit_terms(
        env_cfg, data, before["identification"][0], before["heldout"][0], cfg.stop_margin
    )
    first = {}
    for t in terms:
        first.setdefault(t.joint, t)
    if not any(t.param == "q" and t.share >= SPRING_SHARE for t in first.values()):
        return False
    named = {(e.name, e.target) for e in result.missing_effects}
    laws = {(FEATURE[t.param].same_law[0], t.joint) for t in terms if FEATURE[t.param].same_law}
    if named & laws:
        return False
    errors = corrected_errors(env_cfg, with_terms(result.env_effects, terms), data, cfg)
    current = (result.after_terms or result.after)["heldout"][1].normalized
    if not errors["heldout"][1].normalized < (1 - cfg.stop_margin) * current:
        return False
    log.info("the named effects compensate a spring: %s", "; ".join(map(Term.describe, terms)))
    result.tentative = result.missing_effects + result.tentative
    result.missing_effects = []
    result.terms, result.angle_readings, result.after_terms = terms, angles, errors
    return True


def fit_backend(env_cfg, choice: str) -> str:
    """The backend discovery simulates with (see DiscoverConfig.backend)."""
    if choice == "env":
        return env_cfg.backend
    if choice != "auto":
        return choice
    if env_cfg.backend == "analytic":
        return "analytic"
    try:
        from hds.envs.system import make_simulator

        make_simulator(env_cfg.xml, backend="analytic", timestep=env_cfg.timestep)
    except (ValueError, ImportError, ModuleNotFoundError) as err:
        log.info("fitting on the env's backend %s (analytic: %s)", env_cfg.backend, err)
        return env_cfg.backend
    return "analytic"


def with_backend(env_cfg, backend: str):
    """The env config with another physics backend (a dataclass or a DictConfig)."""
    if env_cfg.backend == backend:
        return env_cfg
    return replace_env(env_cfg, backend=backend)


def replace_env(env_cfg, **changes):
    """The env config with `changes` (a dataclass or a DictConfig)."""
    if dataclasses.is_dataclass(env_cfg):
        return dataclasses.replace(env_cfg, **changes)
    from omegaconf import OmegaConf

    return OmegaConf.merge(env_cfg, changes)


def corrected_errors(env_cfg, effects: list[dict], data: Data, cfg: DiscoverConfig):
    """Residuals and errors, per set, of the env's simulator with `effects` (no candidates)."""
    engine = get_engine(
        replace_env(env_cfg, effects=effects), data.dt, [], cfg.max_delay, cfg.warmup, cfg.horizon
    )
    no_delay = np.zeros(len(engine.model.sim.action_names), np.int32)
    return compare(engine, data, engine.model.nominal, no_delay)


def _effect_dict(spec) -> dict:
    return {"name": spec.name, "target": spec.target, "params": dict(spec.params)}


def structure(loc: Location) -> float:
    """Share of a residual that single features explain: each variable's best eta^2, weighted
    by the variable's share of the (normalized one-step) residual."""
    best = {}
    for row in loc.table:
        best[row["variable"]] = max(best.get(row["variable"], 0.0), row["eta2"])
    return float(sum(s * best.get(v, 0.0) for v, s in zip(loc.variables, loc.share)))


def _cut(shares: list[float], structured: float) -> int:
    """Where the chain's named effects end: at the first whose share (`explained_shares`) is
    below the structured remainder (it and those after it compensate the named laws'
    mismatch), else after the last."""
    return next((i for i, s in enumerate(shares[:-1]) if s < structured), len(shares) - 1)


def explained_shares(selection: Selection) -> list[float]:
    """Each selected effect's share of the base model's held-out k-step MSE, in the order of
    selection, then the share left unexplained (they sum to 1)."""
    mse = [s.heldout_error**2 for s in selection.states]
    base = mse[0]
    if base <= 0:
        return [0.0] * (len(mse) - 1) + [0.0]
    return [(mse[i] - mse[i + 1]) / base for i in range(len(mse) - 1)] + [mse[-1] / base]


def refused_shares(selection: Selection) -> list[tuple[State, float]]:
    """Each state refused as law mismatch with its effect's share of the base model's
    held-out k-step MSE: what it removed beside the others (none if it removed nothing)."""
    base = selection.states[0].heldout_error ** 2
    return [
        (m, max(without.heldout_error**2 - m.heldout_error**2, 0.0) / base if base > 0 else 0.0)
        for m, without in selection.mismatch
    ]


def name_effects(model, states, shares, delay_steps=None) -> list[NamedEffect]:
    """The effects of the last of `states` (a prefix of the selection) with values, units,
    95% CIs and their shares of the held-out error."""
    final = states[-1]
    cis = intervals(model, final, delay_steps) if final.selected else {}
    named = []
    for i, cand in enumerate(final.selected):
        etype = effect_type(cand.name)
        if cand.shifts_actions:
            (param,) = cand.params
            params = {param: int(final.delay[cand.actuator])}
            units = {param: etype.param(param).unit}
        else:
            params = {
                p: _round(final.theta[s]) for p, s in zip(cand.params, cand.slots, strict=True)
            }
            units = {p: model.units[s] for p, s in zip(cand.params, cand.slots, strict=True)}
        ci = {p: [_round(lo), _round(hi)] for p, (lo, hi) in cis.get(cand.key, {}).items()}
        at_joint = {}
        if etype.target_kind == ACTUATOR:  # a control offset as a joint force
            gear = float(model.sim.sys.actuator.gear[model.sim.targets["actuator"][cand.target]])
            at_joint = {
                p: _round(v * gear) for p, v in params.items() if units[p] == "control units"
            }
        named.append(
            NamedEffect(cand.name, cand.target, params, units, ci, float(shares[i]), at_joint)
        )
    return named


def _round(x: float) -> float:
    x = float(x)
    return x if not np.isfinite(x) or x == 0 else float(f"{x:.6g}")


def _separable_count(model, state: State, shown: set[str] = frozenset()) -> int:
    """How many effects, in the order of selection, come before the first whose parameters
    the data cannot separate from an earlier effect's: correlated beyond INSEPARABLE, and
    its value not clearly apart from its no-op. Chosen as the best of the library's
    candidates, such an effect must stand apart at the level corrected for that many
    comparisons (Bonferroni: its 95% interval, which the correlation widens, scaled to
    1 - 0.05 / candidates). That one is a compensation the data cannot tell apart, not named:
    beside MuJoCo's 80 N soft friction, a dead zone of 0.69 [0.009, 1.37] (correlation
    -0.999). A strong correlation alone is not enough: a heavier pole and a damper on its
    hinge correlate at 0.97, yet data that fit both identify each (0.40 [0.30, 0.49]). Nor
    is one the data show once refitted jointly (`shown`, `Selection.shown`): dropping it, the
    other refitted, predicts the held-out episodes worse by more than the law mismatch
    left; beside rail friction, a gain of 0.83 [0.69, 0.97] (correlation 0.97) whose drop
    sends the friction from 20 to 25 N."""
    inseparable = [r for r in correlations(state) if r["inseparable"]]
    if not inseparable:
        return len(state.selected)
    order = {f"{c.key}.{p}": i for i, c in enumerate(state.selected) for p in c.params}
    ci = confidence_intervals(state.theta[state.slots], state.h, state.g, state.misfit, state.views)
    half = dict(zip(state.slots, ci.half, strict=True))
    widen = stats.norm.ppf(1 - 0.025 / len(model.candidates)) / stats.norm.ppf(0.975)
    slot = {f"{c.key}.{p}": s for c in state.selected for p, s in zip(c.params, c.slots)}

    def apart(name: str) -> bool:
        if name.rsplit(".", 1)[0] in shown:
            return True
        s = slot[name]
        return abs(float(state.theta[s]) - float(model.nominal[s])) > widen * half[s]

    clashes = []
    for r in inseparable:
        later = max((r["a"], r["b"]), key=order.__getitem__)
        if not apart(later):
            clashes.append(order[later])
    return min(clashes, default=len(state.selected))


def near_ties(candidates: list[dict], named, margin: float) -> list[str]:
    """Named effects that won their selection round over another effect by less than the
    selection margin (`stop_margin`) of the held-out error: these data barely tell the two
    apart, so the one named may stand in for the other (under steps held for several
    control periods, a first-order lag of a step or two predicts almost what a step of delay
    does). Each from the round's chosen row and its `rival` (`explain.forward_selection`)."""
    keys = {f"{e.name}@{e.target}" for e in named}
    out = []
    for row in candidates:
        rival, key = row.get("rival"), f"{row['name']}@{row['target']}"
        if not (row.get("chosen") and rival and key in keys):
            continue
        own, other = row["heldout_error"], rival["heldout_error"]
        if other < own * (1.0 + margin):
            out.append(
                f"{key} was chosen over {rival['name']}@{rival['target']} in selection round "
                f"{row['round']} by {(other - own) / own:.1%} of the held-out error (held-out "
                f"{own:.4g} against {other:.4g}), less than the selection margin "
                f"{margin:.0%}: these data barely tell the two apart, so {key} may stand in "
                "for the other; record data where they differ"
            )
    return out


def warnings(result: Discovery, cfg: DiscoverConfig) -> list[str]:
    out = []
    for e in result.tentative:
        out.append(
            f"{e.name}@{e.target} lowered the held-out error ({e.explained_fraction:.0%}"
            " of it), but it is a likely compensation: for structure outside the library, "
            "or for a named effect the data cannot separate it from; reported as tentative, "
            "not as a missing effect"
        )
    if result.unexplained_fraction > cfg.unexplained_warning and not result.selection.unidentified:
        top = result.remainder.top
        share = f"{result.unexplained_fraction:.0%} of the held-out prediction error (MSE)"
        if result.structured_unexplained > cfg.unexplained_warning * 0.5 and top:
            out.append(
                f"{share} stays unexplained by the library's effects, and it has a "
                f"structure: the residual of {top['variable']} depends on "
                f"{top['feature']} (eta^2 = {top['eta2']:.2f}); the simulator probably "
                "misses an effect outside the library"
                + (
                    ": "
                    + "; ".join(t.describe() for t in result.terms)
                    + " (added to the corrected model as joint_force_terms: held-out k-step "
                    f"error {result.error('before').normalized:.3g} -> "
                    f"{result.after_terms['heldout'][1].normalized:.3g})"
                    if result.terms
                    else ""
                )
            )
        else:
            out.append(
                f"{share} stays unexplained, with no structure any feature reveals: "
                "measurement noise, or an effect the features do not show"
            )
    if result.angle_readings:  # terms were fitted: how each hinge's angle was read
        out.append(
            "hinge angles read by the term fit: "
            + "; ".join(r.describe() for r in result.angle_readings)
        )
    out += compensations(result.missing_effects, result.terms)
    out += near_ties(result.candidates, result.missing_effects, cfg.stop_margin)
    for e in result.law_mismatch:
        out.append(
            f"{e.name}@{e.target} ({e.fitted()}) is law mismatch (the plant's laws are not exactly "
            f"the library's), not added: it lowered the held-out error by "
            f"{e.explained_fraction:.1%} of it; "
            + (
                e.reason
                or "less than the structure the named effects' residual still has, or less "
                "than the misfit they leave without it, or less of the held-out error than "
                "the model leaves, or with an interval that does not exclude no effect"
            )
        )
    for r in result.correlations:
        if r["inseparable"]:
            out.append(
                f"{r['a']} and {r['b']} correlate at {r['rho']:.3f}: the data separate "
                "them only jointly, and their intervals are wide for it; record data that "
                "excite them differently"
            )
    if result.selection.unidentified:
        out.append(
            f"{result.selection.unidentified} explains more of the gap than any effect the "
            "data can identify, but these data cannot identify it: nothing that would only "
            "compensate for it is named, in the library or beyond it; record data that "
            "identify it"
        )
    by_reason: dict[str, list[str]] = {}
    for r in result.identifiability:
        if not (r.identifiable or r.structural):
            by_reason.setdefault(r.reason, []).append(r.key)
    for reason, keys in by_reason.items():
        out.append(f"not identifiable from these data, so not fitted: {', '.join(keys)}: {reason}")
    for e in result.missing_effects:
        params = {p.name: p for p in effect_type(e.name).params}
        reach = [
            f"{p} [{lo:.4g}, {hi:.4g}]"
            for p, (lo, hi) in e.ci95.items()
            if not params[p].discrete and lo <= params[p].nominal <= hi
        ]
        if reach and len(reach) == len(e.ci95):
            out.append(
                f"{e.name}@{e.target} is named because the held-out episodes show it "
                "(without it, the others refitted, they are predicted worse by more than "
                "the named laws' mismatch), although its interval reaches no effect "
                f"({'; '.join(reach)}): that mismatch widens it; its value is uncertain, "
                f"its presence is not ({e.explained_fraction:.1%} of the held-out error, "
                "in the order of selection)"
            )
        for p, (lo, hi) in e.ci95.items():
            if not (np.isfinite(lo) and np.isfinite(hi)):
                out.append(
                    f"{e.name}@{e.target}.{p} is not determined by the data (its "
                    "confidence interval is unbounded)"
                )
    return out
