"""Step 3, explain: which effects of the library account for the gap.

Greedy forward selection on held-out error. Each round fits, in one batched call, every
candidate (effect x place) together with the effects already selected, all of them refitted
jointly on the identification episodes' k-step prediction error (Levenberg-Marquardt through
the differentiable simulator; action delays by enumeration: each delay is a candidate of its
own). The candidate whose fitted model predicts the HELD-OUT episodes best is added if it
lowers their error by a meaningful margin (`stop_margin`, relative, and `min_improvement`,
absolute); otherwise selection stops. A spurious effect fitted to noise lowers the
identification error a little but not the held-out one, so with nothing missing nothing is
named. Once selection ends, an effect chosen early for another at its own place is
exchanged for it where that predicts the held-out episodes better (`_exchange`: a lag taken
for a delay), and an effect that removes less of the identification misfit than
the final model still leaves is law mismatch, not named, and so is one whose interval does
not exclude no effect unless the held-out episodes show it (`_refuse_law_mismatch`,
`_shown_on_held_out`).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy import stats

from hds.discover.fit import Engine, confidence_intervals, curvature_inverse
from hds.discover.model import Candidate
from hds.effects.library import effect_type
from hds.utils.runtime import cpu_workers

log = logging.getLogger("hds")


@dataclass
class State:
    """A model in the search: the selected candidates with their fitted values."""

    selected: list[Candidate]
    theta: np.ndarray  # [N]
    delay: np.ndarray  # [n_act]
    heldout_error: float  # normalized RMSE of k-step predictions on the held-out episodes
    identification_error: float
    h: np.ndarray | None = None  # Gauss-Newton matrix over `slots`
    g: np.ndarray | None = None  # per-episode gradients over `slots`
    slots: list[int] = field(default_factory=list)
    # identification sum of squared normalized residuals above the measurement noise: what
    # the laws of the selected effects fail to fit (the size of the model's own error)
    misfit: float = 0.0
    # H [V, M, M] and G [V, E, M] of each view of the residuals (`Engine.views`)
    views: tuple[np.ndarray, np.ndarray] | None = None
    # the identification windows' estimated initial states [W, n_obs] (estimated initial
    # states only): where the fits of effects added to this model start theirs
    z: np.ndarray | None = None
    # a state refused as law mismatch (`Selection.mismatch`): which rule refused its last
    # effect, with the numbers the rule compared
    refused_because: str = ""

    @property
    def keys(self) -> set[str]:
        return {c.key for c in self.selected}

    def intervals(self, mismatch: bool = True):
        """`confidence_intervals` of the fitted slots: the noise's and (`mismatch`) the
        laws' mismatch's."""
        extra = (self.misfit, self.views) if mismatch else ()
        return confidence_intervals(self.theta[self.slots], self.h, self.g, *extra)

    def half_widths(self, mismatch: bool = True) -> dict[int, float]:
        """Each fitted slot's 95% half-width (`intervals`); inf where the data do not
        determine it."""
        return dict(zip(self.slots, map(float, self.intervals(mismatch).half)))


@dataclass
class Selection:
    states: list[State]  # the base model, then one state per effect added (refitted)
    rounds: list[list[dict]]  # every candidate's fit, per round
    stopped: str  # why selection ended
    dropped: list[Candidate] = field(default_factory=list)  # proxies replaced by a later effect
    # each candidate refused as law mismatch: the state it would have made (its effect last)
    # and the state without it
    mismatch: list[tuple[State, State]] = field(default_factory=list)
    # a candidate the data cannot identify that explains more than any they can: selection
    # stopped before naming a compensation for it
    unidentified: str = ""
    # keys of the final model's effects that trade off against another, and whose drop (the
    # others refitted jointly) raises the held-out error by more than the law mismatch left:
    # the data show them, however wide the trade-off makes their intervals (`_shown`)
    shown: set[str] = field(default_factory=set)
    # the chain's effects, in their order of selection, when the search ended and before the
    # final judgement (`_finish`): what `judge_path` refits with other initial states
    path: list[Candidate] = field(default_factory=list)

    @property
    def final(self) -> State:
        return self.states[-1]


def _slot_width(model) -> int:
    return max((len(c.slots) for c in model.candidates), default=1)


def _batch(model, state: State, width: int):
    """theta0 [C, N], slots [C, M], delay [C, n_act] of every candidate added to `state`."""
    n_c = len(model.candidates)
    theta0 = np.tile(state.theta, (n_c, 1))
    delay = np.tile(state.delay, (n_c, 1))
    slots = -np.ones((n_c, width), np.int32)
    for i, cand in enumerate(model.candidates):
        own = [] if cand.key in state.keys else list(cand.slots)
        theta0[i, own] = model.start[own]
        chosen = state.slots + own
        slots[i, : len(chosen)] = chosen
        if cand.shifts_actions:
            delay[i, cand.actuator] = cand.steps
    return theta0, slots, delay


def _rival(model, fresh: list[int], decided, best: int) -> dict | None:
    """The round's best fresh candidate of another effect than `best`'s (a delay's other
    lengths are the same effect): {name, target, heldout_error}, or None where none was
    fitted. Where it comes close, the data barely tell the two apart
    (`hds.discover.workflow.near_ties`)."""
    others = [j for j in fresh if model.candidates[j].key != model.candidates[best].key]
    others = [j for j in others if np.isfinite(decided[j])]
    if not others:
        return None
    j = min(others, key=lambda i: decided[i])
    cand = model.candidates[j]
    return {"name": cand.name, "target": cand.target, "heldout_error": float(decided[j])}


def _round_line(round_index: int, model, fresh: list[int], decided) -> str:
    """A selection round's progress: the best candidate it may add, by the error it is judged
    on (a screen's row, a refinement or a selected effect's refit is never added)."""
    head = f"selection round {round_index}: {len(model.candidates)} candidates fitted"
    finite = [j for j in fresh if np.isfinite(decided[j])]
    if not finite:
        return f"{head}, none left to add"
    j = min(finite, key=lambda i: decided[i])
    cand = model.candidates[j]
    return f"{head}, the best to add {cand.name}@{cand.target} (held-out error {decided[j]:.3g})"


def candidate_params(model, cand: Candidate, theta, delay) -> dict[str, float]:
    if cand.shifts_actions:
        return {cand.params[0]: int(delay[cand.actuator])}
    return {p: float(theta[s]) for p, s in zip(cand.params, cand.slots, strict=True)}


def forward_selection(
    engine: Engine,
    ident,
    heldout,
    cfg,
    estimate: bool = False,
    floor: float = 0.0,
    banned=(),
    progress=None,
    carried: float = 0.0,
) -> Selection:
    """Select effects; `ident` and `heldout` are `Data.arrays(...)` of the two episode sets;
    `estimate`: fit each window's initial state too (noisy data); `floor`: the held-out
    normalized RMSE measurement noise alone leaves; `banned`: keys of candidates the data
    cannot identify (fitted, never selected); `progress(stage)`: told as each round ends;
    `carried`: the mean squared normalized residual that the measured initial states' error
    carries through the identification windows (`Engine.carried_noise`; measured states
    only), part of the noise floor a correct model would still leave."""
    model = engine.model
    fit = _fitter(engine, ident, heldout, cfg, estimate, floor, carried)
    state = _base_state(fit)
    states, rounds, dropped, mismatch = [state], [], [], []
    stopped, unidentified = f"reached discover.max_effects = {cfg.max_effects}", ""
    unidentifiable, banned = set(banned), set(banned)
    if not any(c.key not in banned for c in model.candidates):
        return Selection(states, rounds, "the library has no candidate the data can identify")
    # each round adds one effect, and may drop one: at most twice max_effects rounds
    for round_index in range(1, 2 * cfg.max_effects + 1):
        if len(state.selected) >= cfg.max_effects:
            break
        batch = fit(state, banned)
        theta, delay, held, loss = batch.theta, batch.delay, batch.held, batch.loss
        # the decisions compare fits with estimated states only, never a screen's row
        decided = np.where(batch.screened, np.inf, held)
        rows = []
        for i, cand in enumerate(model.candidates):
            rows.append(
                {
                    "name": cand.name,
                    "target": cand.target,
                    "round": round_index,
                    "params": candidate_params(model, cand, theta[i], delay[i]),
                    "heldout_error": float(held[i]),
                    "identification_error": float(np.sqrt(loss[i])),
                    "new": cand.key not in state.keys,
                    "iterations": int(batch.iterations[i]),
                    # fitted with the windows' states held (`_Fitter.__call__`), not estimated
                    "screened": bool(batch.screened[i]),
                }
            )
        rounds.append(rows)
        # the candidates selection may add (a refit of the selected effects keeps their keys)
        fresh = [
            i
            for i, c in enumerate(model.candidates)
            if c.key not in state.keys and c.key not in banned and not _refinement(c)
        ]
        if progress:
            progress(_round_line(round_index, model, fresh, decided))
        # the selected effects refitted together (a candidate already selected adds nothing
        # new: its row is a longer refit of the current model, or another delay length)
        refits = [i for i, c in enumerate(model.candidates) if c.key in state.keys]
        if refits:
            i = min(refits, key=lambda j: decided[j])
            if held[i] < state.heldout_error:
                state = fit.state(state.selected, batch, i)
                states[-1] = state
        if not fresh:
            stopped = "every candidate the data can identify is selected"
            break
        if state.heldout_error <= floor * (1 + cfg.stop_margin):
            stopped = (
                f"the held-out error, {state.heldout_error:.3g} (normalized RMSE), is at the "
                f"noise floor {floor:.3g}: nothing above the measurement noise is left"
            )
            break
        needed = max(cfg.stop_margin * state.heldout_error, cfg.min_improvement)
        best = min(fresh, key=lambda j: decided[j])
        rival = _rival(model, fresh, decided, best)
        # judged as refitted jointly: where it trades off against an effect already in
        # (friction high and gain low), the round's fit from the current values may stop
        # in the trade-off's valley and understate what it adds
        grown = _settle(fit, fit.state(state.selected + [model.candidates[best]], batch, best))
        drop = state.heldout_error - grown.heldout_error
        label = model.candidates[best].label
        compensated = _unidentifiable_explains_more(model, unidentifiable, decided, best)
        if not drop >= needed:
            # no swap for a compensation of what the data cannot identify (below)
            swapped = None if compensated else _swap(fit, states, grown)
            if swapped is None:
                stopped = (
                    f"the best remaining candidate, {label}, lowers held-out error by "
                    f"{max(drop, 0.0):.3g} (normalized RMSE), less than the margin {needed:.3g}"
                )
                break
            states, gone = swapped
            dropped += gone
            banned.update(c.key for c in gone)
            state = states[-1]
            continue
        if compensated:
            unidentified = compensated
            stopped = (
                f"the best remaining candidate, {unidentified}, is one the data cannot "
                f"identify (see identifiability): {label}, the best the data can identify, "
                f"would only compensate for it, so it is not named; record data that "
                f"identify {unidentified}"
            )
            break
        # what is left once the best candidate is no effect is the named laws' mismatch,
        # which further candidates would only compensate
        if _within_mismatch(model, grown, model.candidates[best], cfg.min_scale_change):
            reason = "its change is within its noise interval or the scale margin"
            mismatch.append((dataclasses.replace(grown, refused_because=reason), state))
            stopped = f"the best remaining candidate, {label}, is law mismatch, not an effect"
            break
        state = grown
        rows[best].update(chosen=True, rival=rival)
        states.append(state)
        states, gone = _drop_proxies(fit, states)
        dropped += gone
        banned.update(c.key for c in gone)
        state = states[-1]
    states, exchanged = _exchange(fit, states, banned)
    dropped += exchanged
    banned.update(c.key for c in exchanged if c.key not in states[-1].keys)
    path = list(states[-1].selected)
    split_states, split = _split_proxy(fit, states, banned)
    if split:
        # the pair is judged as any final model is; it stands only if both of it survive,
        # else the effect it replaced stays (a pair cut to one is no better than it)
        pair = [c for c in split_states[-1].selected if c.key not in states[-1].keys]
        kept = [m for m in mismatch if m[0].selected[-1].key not in split_states[-1].keys]
        trial = _finish(fit, split_states, kept)
        if all(c.key in trial[-1].keys for c in pair):
            states, mismatch, dropped = trial, kept, dropped + split
            path = list(split_states[-1].selected)
        else:
            log.info("the pair %s did not stand as named", " and ".join(c.key for c in pair))
            split = []
    if not split:
        states = _finish(fit, states, mismatch)
    states, refined = _refine(fit, states, banned, mismatch)
    dropped += refined
    shown = _shown(fit, states[-1])
    return Selection(states, rounds, stopped, dropped, mismatch, unidentified, shown, path)


def judge_path(
    engine: Engine,
    ident,
    heldout,
    cfg,
    path: list[Candidate],
    estimate: bool = False,
    floor: float = 0.0,
    carried: float = 0.0,
) -> Selection:
    """Another search's selection (`Selection.path`: its effects in their order) refitted with
    these fits' initial states (`estimate`) and judged as any selection's final model is
    (`_finish`: settled, then each effect refused that earns less than the model's mismatch),
    with no search of its own: each prefix of the path fitted jointly from the library's
    starting values, in one batched fit. What the initial-state choice compares
    (`hds.discover.workflow.choose_initial_states`): the held-out episodes judge both starts'
    fits of the same effects, not two searches' different paths. Arguments as
    `forward_selection`'s."""
    fit = _fitter(engine, ident, heldout, cfg, estimate, floor, carried)
    base = _base_state(fit)
    keys = ", ".join(c.key for c in path) or "none"
    stopped = f"the effects another search selected ({keys}), refitted and judged"
    if not path:
        return Selection([base], [], stopped)
    start = dataclasses.replace(base, theta=engine.model.start.copy())
    states = [base] + fit.sets(start, [path[:n] for n in range(1, len(path) + 1)])
    mismatch: list[tuple[State, State]] = []
    states = _finish(fit, states, mismatch)
    shown = _shown(fit, states[-1])
    return Selection(states, [], stopped, [], mismatch, "", shown, list(path))


def by_contribution(
    engine: Engine,
    ident,
    heldout,
    cfg,
    selection: Selection,
    estimate: bool = False,
    floor: float = 0.0,
    carried: float = 0.0,
) -> Selection:
    """The selection's chain with its final effects in the order of what each adds beside
    the others (what dropping it, the others refitted, adds to the held-out error; the most
    first), each prefix (the whole set last) refitted from the final fit's values.
    A chain keeps the search's order through refusals and swaps, where an effect chosen early
    can add little until a later one is in: an arm's friction chosen before the delay that a
    lag first stood in for removes less held-out error in its place than the model's
    structured remainder, and a cut at it would refuse the delay (80% of the error) as law
    mismatch with it. Unchanged where the order is already that. Arguments as
    `forward_selection`'s."""
    if len(selection.final.selected) < 2:
        return selection
    return _by_contribution(
        _fitter(engine, ident, heldout, cfg, estimate, floor, carried), selection
    )


def _by_contribution(fit, selection: Selection) -> Selection:
    final = selection.final
    chosen = final.selected
    reduced = fit.sets(final, [[c for c in chosen if c is not out] for out in chosen])
    adds = np.array([r.heldout_error for r in reduced])
    order = [chosen[i] for i in np.argsort(-adds, kind="stable")]
    if order == chosen:
        return selection
    log.info(
        "the chain reordered by what each effect adds beside the others: %s",
        ", ".join(c.key for c in order),
    )
    states = fit.sets(final, [order[:n] for n in range(1, len(order) + 1)])
    return dataclasses.replace(selection, states=[selection.states[0], *states])


def _fitter(engine: Engine, ident, heldout, cfg, estimate, floor, carried) -> _Fitter:
    """The batched fits of a selection: one slot width per bucket of cfg.slot_buckets below
    max_effects, and max_effects'."""
    sw = _slot_width(engine.model)
    sizes = sorted(
        {b * sw for b in cfg.slot_buckets if b < cfg.max_effects} | {max(cfg.max_effects, 1) * sw}
    )
    return _Fitter(engine, ident, heldout, cfg, estimate, sizes, sw, floor, carried)


def _base_state(fit: _Fitter) -> State:
    """The simulator as it is (no effect added): its errors and misfit."""
    engine = fit.engine
    theta = engine.model.nominal.copy()
    delay = np.zeros(len(engine.model.sim.action_names), np.int32)
    ident_error = float(engine.errors(theta[None], delay[None], fit.ident)[0])
    return State(
        [],
        theta,
        delay,
        float(engine.errors(theta[None], delay[None], fit.heldout)[0]),
        ident_error,
        misfit=fit.misfit(ident_error**2),
    )


def _finish(fit, states: list[State], mismatch: list) -> list[State]:
    """The selection's last model settled and judged (`_refuse_law_mismatch`,
    `_refuse_within_heldout_mismatch`; each refusal appended to `mismatch`): the chain."""
    states = list(states)
    states[-1] = _settle(fit, states[-1])
    shown: set[str] = set()
    states = _refuse_law_mismatch(fit, states, mismatch, shown)
    return _refuse_within_heldout_mismatch(fit, states, mismatch, shown)


TRADE_OFF = 0.5  # |correlation| of two effects' parameters above which their fits trade off


def trade_offs(state: State) -> np.ndarray:
    """[selected] whether each effect's parameters correlate with another effect's beyond
    TRADE_OFF, by the fit's curvature (H^-1: defined without noise too)."""
    out = np.zeros(len(state.selected), bool)
    if state.h is None or len(state.selected) < 2:
        return out
    inv, _ = curvature_inverse(state.h)
    d = np.sqrt(np.maximum(np.diag(inv), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = np.abs(np.nan_to_num(inv / np.outer(d, d)))
    slot_owner = {s: i for i, c in enumerate(state.selected) for s in c.slots}
    owner = np.array([slot_owner.get(s, -1) for s in state.slots])
    for i in range(len(state.selected)):
        mine = owner == i
        block = corr[np.ix_(mine, ~mine)]
        out[i] = bool(block.size and block.max() > TRADE_OFF)
    return out


def trades_off(state: State) -> bool:
    """Whether the newest effect trades off against an earlier one (`trade_offs`)."""
    return bool(state.selected) and bool(trade_offs(state)[-1])


def _settle(fit, state: State) -> State:
    """The state's effects refitted jointly from their starting values (not from the values
    the earlier effects took alone), where the newest trades off against an earlier one
    (`trades_off`); the better of the two fits by identification error. Friction fitted
    alone takes up part of a gain loss (22 N for 18); a gain added from there can settle
    in the valley of the trade-off (0.75 for 0.85), and a share judged there is too small:
    the joint refit from the start finds both (18.4 N, 0.82)."""
    if not trades_off(state):
        return state
    model = fit.engine.model
    (fresh,) = fit.sets(dataclasses.replace(state, theta=model.start.copy()), [state.selected])
    better = fresh.identification_error < state.identification_error
    return fresh if better and np.isfinite(fresh.heldout_error) else state


def _swap(fit, states: list[State], grown: State):
    """Where the best remaining candidate does not earn its place: whether it replaces one
    already selected (a floating search's swap). Added (`grown`), it may make an earlier
    effect redundant (`_drop_proxies`); if the model without it predicts the held-out
    episodes better than the current model, of as many effects, the swap is kept. A gain
    chosen first for a heavier, damped pole (each of which alone explains little) is
    replaced once both are in. Returns (the states, the replaced candidates) or None."""
    current = states[-1]
    trial, gone = _drop_proxies(fit, [*states, grown])
    if not gone or not trial[-1].heldout_error < current.heldout_error:
        return None
    return trial, gone


def _exchange(fit, states: list[State], banned) -> tuple[list[State], list[Candidate]]:
    """Once selection has ended: whether an effect chosen early stands in for another at its
    own place, which forward selection, never revisiting a choice, cannot see. A lag whose
    time constant is one step wins the first round against that step of delay while the
    inertial errors hide how the two differ; once the errors are in, the delay predicts
    better, but a second effect at the motor never earns the margin, and the selection cap
    may stop the search first (a lab Furuta: held-out 0.030 with the lag, 0.020 with the
    delay). For each selected effect, every candidate at its target (actuator, joint, body
    or sensor) not selected, a delay's other lengths among them, takes its place, all
    refitted jointly from the current values (a new effect's own from the library's start);
    the best exchange stands where it predicts the held-out episodes better by
    `min_improvement`. Not by the relative
    `stop_margin`, which an effect added must clear: an exchange adds no effect, so there is
    no growth of the model to guard against, and the absolute floor keeps near-equivalents
    (a mass scale and a centre of mass on one body) from trading places on noise. Repeated
    while one stands, at most once per effect.
    Returns (the chain rebuilt with the exchanges, the effects exchanged out)."""
    model, cfg = fit.engine.model, fit.cfg
    out: list[Candidate] = []
    for _ in range(len(states[-1].selected)):
        state = states[-1]
        trials = [
            (j, c, state.selected[:j] + [c] + state.selected[j + 1 :])
            for j, named in enumerate(state.selected)
            for c in model.candidates
            if c.target == named.target
            and c not in state.selected
            and (c.key not in state.keys or c.key == named.key)  # a delay's other lengths
            and c.key not in banned
            and c not in out
            and not _refinement(c)
        ]
        if not trials:
            break
        start = _from_library_start(model, state)
        fitted = fit.sets(start, [chosen for _, _, chosen in trials])
        held = np.array([f.heldout_error for f in fitted])
        held = np.where(np.isfinite(held), held, np.inf)
        best = int(np.argmin(held))
        (j, c, chosen), trial = trials[best], fitted[best]
        better = state.heldout_error - held[best] >= cfg.min_improvement
        log.info(
            "%s %s %s: held-out error %.4g -> %.4g",
            c.label,
            "takes the place of" if better else "would not take the place of",
            state.selected[j].label,
            state.heldout_error,
            trial.heldout_error,
        )
        if not better:
            break
        out.append(state.selected[j])
        states = _chain_replacing(fit, states, j, chosen, start, trial)
    return states, out


def _from_library_start(model, state: State) -> State:
    """The state with every parameter it has not fitted at the library's start: where a
    fit of its effects with others in place of one of them starts."""
    theta = model.start.copy()
    theta[state.slots] = state.theta[state.slots]
    return dataclasses.replace(state, theta=theta)


def _chain_replacing(fit, states: list[State], j: int, chosen, start: State, trial: State):
    """The chain with the j-th selected effect replaced (`chosen`: the new selection,
    fitted as `trial`): the states before it, the prefixes of the new order refitted from
    `start`, then `trial`."""
    prefixes = [chosen[:n] for n in range(j + 1, len(chosen))]
    return states[: j + 1] + fit.sets(start, prefixes) + [trial]


def _split_proxy(fit, states: list[State], banned) -> tuple[list[State], list[Candidate]]:
    """Whether a selected effect stands for two others at its place that only together
    beat it; forward selection, adding one effect at a time, cannot find such a pair. A
    bearing's dry friction takes the same energy per swing, most felt at small swings, an
    arm's air drag takes most at large ones: over a middle range of amplitudes the two
    together lose per swing about what viscous damping does, so viscous damping is chosen
    first, and neither of the two improves on it alone or beside it (the real single
    pendulum, experiments/multiarm_pendulum). For each selected friction law (an effect with
    a `friction` parameter), every pair of unselected friction laws on its joint replaces
    it, fitted jointly with the others (theirs from the current values, the pair's from its
    start). The best pair is kept where it predicts the held-out episodes better than the
    current model by the selection margin, within discover.max_effects, and the data show
    each of the two (`_within_mismatch`: not a fit of the noise). Returns (the chain rebuilt
    with the pair in the replaced effect's stead, [the replaced effect]) or (states, [])."""
    from itertools import combinations

    model, cfg = fit.engine.model, fit.cfg
    state = states[-1]
    if len(state.selected) + 1 > cfg.max_effects:
        return states, []
    laws = {
        c.key
        for c in model.candidates
        if effect_type(c.name).friction and c.slots and not _refinement(c)
    }
    trials = []
    for j, out in enumerate(state.selected):
        if out.key not in laws:
            continue
        free = [
            c
            for c in model.candidates
            if c.key in laws
            and c.target == out.target
            and c.key not in state.keys
            and c.key not in banned
        ]
        # the pair in the replaced law's place of the order: the chain's prefixes, whose
        # increments are the effects' shares, then grow as selection found them (an inertia
        # selected after the law, alone first in the chain, predicts worse than no effect)
        before, after = state.selected[:j], state.selected[j + 1 :]
        trials += [(j, before + [a, b] + after) for a, b in combinations(free, 2)]
    if not trials:
        return states, []
    start = _from_library_start(model, state)  # the others from where they are
    fitted = fit.sets(start, [chosen for _, chosen in trials])
    best = int(np.argmin([f.heldout_error for f in fitted]))
    (j, chosen), pair = trials[best], fitted[best]
    laws = chosen[j : j + 2]
    better = pair.heldout_error < (1.0 - cfg.stop_margin) * state.heldout_error
    shown = not any(_within_mismatch(model, pair, c, cfg.min_scale_change) for c in laws)
    if not (better and shown and np.isfinite(pair.heldout_error)):
        return states, []
    log.info(
        "%s stood for %s together: held-out error %.4g -> %.4g",
        state.selected[j].key,
        " and ".join(c.key for c in laws),
        state.heldout_error,
        pair.heldout_error,
    )
    return _chain_replacing(fit, states, j, chosen, start, pair), [state.selected[j]]


def _refinement(cand: Candidate) -> str:
    """The effect a candidate refines (`Effect.refines`: its law holds that one's), or ''."""
    refines = effect_type(cand.name).refines
    return refines[0] if refines else ""


def _refine(fit, states: list[State], banned, mismatch: list) -> tuple[list[State], list]:
    """Once the final model is judged: whether a named effect's refinement (`Effect.refines`:
    a law that holds the named one's as a special case, a dry friction with a Stribeck peak
    for Coulomb friction) predicts better in its place. Coulomb's law cannot fit a friction
    whose static level is above its sliding one: its fit lands between the two, and a mass
    or gain compensates. The refinement starts from the named effect's values (its extra
    parameters from their start: no peak), fitted jointly with the others, and takes the
    named one's place where, as any effect added by selection must, it predicts the
    held-out episodes better by the selection margin (`stop_margin`), the data show its
    extra parameters (their noise intervals exclude their no-op, `_within_mismatch`) and
    its gain in held-out MSE is at least what the model leaves above the noise (the
    held-out share rule, `_shown_on_held_out`). The refined chain is then judged again
    (`_finish`): an effect that only compensated the named law's mismatch (a heavier cart
    for the static peak) may now be law mismatch. The refinement stands only if it survives
    that judgement; otherwise the model stays as it was. One joint at a time, the best first.
    Returns (the chain, [the effects refined])."""
    model, cfg = fit.engine.model, fit.cfg
    refined = []
    while True:
        state = states[-1]
        trials = []
        for j, named in enumerate(state.selected):
            for r in model.candidates:
                if (
                    _refinement(r) == named.name
                    and r.target == named.target
                    and r.key not in state.keys
                    and r.key not in banned
                ):
                    trials.append((j, r, state.selected[:j] + [r] + state.selected[j + 1 :]))
        if not trials:
            return states, refined
        theta = _from_library_start(model, state).theta
        for j, r, _ in trials:  # the shared parameters from the named effect's values
            named = state.selected[j]
            for p, s in zip(r.params, r.slots, strict=True):
                if p in named.params:
                    theta[s] = state.theta[named.slots[named.params.index(p)]]
        start = dataclasses.replace(state, theta=theta)
        fitted = fit.sets(start, [chosen for _, _, chosen in trials])
        gains = [state.heldout_error**2 - f.heldout_error**2 for f in fitted]
        best = int(np.argmax(gains))
        (j, r, chosen), trial = trials[best], fitted[best]
        named = state.selected[j]
        # the parameter by which it differs (a peak), not one that means nothing without it
        s = r.slots[r.params.index(effect_type(r.name).refines[1])]
        shown = abs(float(trial.theta[s] - model.nominal[s])) > trial.half_widths(False)[s]
        better = trial.heldout_error < (1.0 - cfg.stop_margin) * state.heldout_error
        enough = gains[best] >= trial.misfit / max(fit.count, 1.0)
        if not (better and shown and enough and np.isfinite(trial.heldout_error)):
            log.info(
                "%s does not refine %s: held-out error %.4g -> %.4g (margin %s), peak shown "
                "by its noise interval %s, held-out MSE gain %.3g against %.3g left",
                r.key,
                named.key,
                state.heldout_error,
                trial.heldout_error,
                better,
                shown,
                gains[best],
                trial.misfit / max(fit.count, 1.0),
            )
            return states, refined
        kept = list(mismatch)
        judged = _finish(fit, _chain_replacing(fit, states, j, chosen, start, trial), kept)
        if r.key not in judged[-1].keys:
            log.info("the refinement %s of %s did not stand as named", r.key, named.key)
            return states, refined
        log.info(
            "%s refines %s: held-out error %.4g -> %.4g",
            r.key,
            named.key,
            state.heldout_error,
            trial.heldout_error,
        )
        states, refined = judged, refined + [named]
        mismatch[:] = kept
        banned = set(banned) | {named.key}


def _unidentifiable_explains_more(model, keys: set[str], held, best: int) -> str:
    """The label of a candidate the data cannot identify (`keys`) whose fit predicts the
    held-out episodes better than the best identifiable one (`best`), or ''. Its value is
    not determined (a cart friction holds still fits at any force above the excitation's),
    but that it explains more of the residual is: an identifiable effect elsewhere (a damped
    pole for a stuck cart) would only compensate for it."""
    rows = [
        i
        for i, c in enumerate(model.candidates)
        if c.key in keys and np.isfinite(held[i]) and held[i] < held[best]
    ]
    return model.candidates[min(rows, key=lambda i: held[i])].label if rows else ""


def _within_mismatch(model, state: State, cand: Candidate, min_scale_change: float) -> bool:
    """Whether the newly added continuous candidate is no effect the data show: its noise
    interval holds its no-op value, or, multiplicative (gain, mass scale: no-op 1), it
    changes its quantity by less than `scale_margin`: what the step's own treatment of the
    joint damping could make look like more inertia. (The law-mismatch part of the intervals
    is left out here: while an effect is still missing, the misfit holds it, and would refuse
    real effects.)"""
    if not cand.slots or not state.slots:
        return False
    if all(model.nominal[s] == 1.0 for s in cand.slots):
        margin = scale_margin(model, state, min_scale_change)
        if all(abs(state.theta[s] - 1.0) < margin for s in cand.slots):
            return True
    half = state.half_widths(mismatch=False)
    return all(abs(float(state.theta[s]) - float(model.nominal[s])) <= half[s] for s in cand.slots)


def scale_margin(model, state: State, min_scale_change: float = 0.0) -> float:
    """The least relative change a gain, mass or inertia scale (no-op 1) must make to be
    named: the relative inertia that the step's treatment of joint damping adds, or
    `min_scale_change` where that is larger. MuJoCo's Euler, and every backend of hds after
    it, integrates damping implicitly, qdd = (M + h D)^-1 (...), which acts as h D more
    inertia against a plant that integrates it otherwise (a real one, continuous in time;
    MuJoCo's RK4; a backend with an explicit damping force): up to h b_j / M_jj on joint j,
    b_j its damping as the model has it (the MJCF's, the env's effects' and the selected
    viscous damping's), M_jj its inertia at the reference pose (MuJoCo's dof_invweight0).
    The largest over the joints (a bound: a scale of one body moves the coupled inertia of
    all of them): on the cart-pole at 20 ms 4.0%, its pole's hinge with the MJCF's 1 N m
    s/rad (the cart's 10 N s/m alone: 1.7%); 7e-5 on the real single pendulum, 2.2e-4 N m
    s/rad at 1 ms. A fixed margin instead (3%, sized for the cart-pole when its damping was
    an explicit force) refused the real pendulum's 0.28% period correction, an inertia
    about the COM of 1.08 [1.01, 1.15] (experiments/multiarm_pendulum)."""
    sim = model.sim
    damping = np.array(sim.sys.dof.damping, dtype=np.float64)
    joints = sim.targets["joint"]
    fitted = [
        (e.target, float(e.params.get("coefficient", 0.0)))
        for e in model.env_effects
        if e.name == _DAMPING
    ]
    fitted += [
        (c.target, float(state.theta[c.slots[0]])) for c in state.selected if c.name == _DAMPING
    ]
    for target, coefficient in fitted:
        damping[joints[target]] += coefficient
    inverse_inertia = np.array(sim.sys.dof_invweight0, dtype=np.float64)
    artifact = sim.timestep * float(np.max(damping * inverse_inertia, initial=0.0))
    return max(artifact, min_scale_change)


_DAMPING = "viscous_damping"  # the library's effect that adds to a joint's damping


def _drop_proxies(fit, states: list[State]):
    """Try dropping each selected effect but the newest, the others refitted: an effect
    chosen early as a proxy (a lag for a delay) no longer earns its place once the real one
    is in, i.e. dropping it raises the held-out error by less than the margin an effect
    must bring to be added. Repeated while one drops out (a gain and a heavier cart, both
    taken for a heavier, damped pole, leave once it is in). Returns the states (the chain
    rebuilt without them) and the dropped candidates."""
    gone = []
    while len(states[-1].selected) >= 2:
        state = states[-1]
        sets = [[c for c in state.selected if c is not out] for out in state.selected[:-1]]
        reduced = fit.sets(state, sets)
        j = int(np.argmin([s.heldout_error for s in reduced]))
        rise = reduced[j].heldout_error - state.heldout_error
        if rise >= max(fit.cfg.stop_margin * reduced[j].heldout_error, fit.cfg.min_improvement):
            break
        gone.append(state.selected[j])
        states = _chain_without(fit, states, j, reduced[j])
    return states, gone


def _chain_without(fit, states: list[State], j: int, reduced: State) -> list[State]:
    """The chain of states with the j-th selected effect taken out: the states before it,
    then the prefixes of the remaining order refitted, then `reduced` (all but it)."""
    kept = reduced.selected
    prefixes = [kept[:n] for n in range(j + 1, len(kept))]
    before = states[: min(j, len(kept) - 1) + 1]  # the last effect out: reduced is its prefix
    return before + fit.sets(states[-1], prefixes) + [reduced]


def _refuse_law_mismatch(
    fit, states: list[State], refused: list[tuple[State, State]], shown: set[str] | None = None
) -> list[State]:
    """Once selection has ended, what the final model still fails to fit above the
    measurement noise (its `misfit`) is the named laws' mismatch with the plant's (or
    structure outside the library). An effect that earns less than that, i.e. dropping it
    alone (the others refitted) raises the misfit by less than the misfit itself, is a
    compensation for that mismatch, not a finding: a lag standing in for MuJoCo's soft
    friction, a heavier cart for its stiction. Judged by what each effect adds beside all the
    others, not by its order of selection (an effect chosen first takes the largest share,
    even one that only compensates the one chosen next). The weakest is taken out, the rest
    refitted, until every effect earns more; each refused state (its effect last) is
    appended to `refused` with the state without it. An effect whose 95% interval, law
    mismatch included, does not exclude no effect (`_indistinct`) is refused the same way: a
    cart 1.05 [1.00, 1.11] times heavier beside 80 N of MuJoCo's soft friction, which the
    misfit alone kept, is refused; a gain of 0.83 [0.69, 0.97] beside rail friction and a
    delay, whose drop (the friction refitted to 25 N for 20) triples what the model leaves,
    is kept.

    Either rule gives way where the held-out episodes show the effect
    (`_shown_on_held_out`). On a lab plant the misfit also holds what no library law takes on
    (cogging, a dead band, Stribeck peaks): Furuta draw 202's one-shot refused a true step
    of delay that removed 28.8 of a misfit of 56.4, and a lab cart's rail friction of 7.8
    [0, 20.8] N that removed 86% of the held-out error was refused for its interval.
    What the held-out episodes show beside all the others (the first model judged) stays
    shown while others are refused: each refusal moves the refused effect's share into what
    the model leaves, so without that a compensation refused first could take a real effect
    with it (Furuta draws 201 and 203: a gain and a friction, then the delay). Two
    substitutes for one mismatch are each shown beside the other by little, and are both
    refused still. Those keys are added to `shown` (for `_refuse_within_heldout_mismatch`).
    Returns the rebuilt chain."""
    model = fit.engine.model
    shown = set() if shown is None else shown
    first = True
    while states[-1].selected:
        state = states[-1]
        sets = [[c for c in state.selected if c is not out] for out in state.selected]
        reduced = fit.sets(state, sets) if len(sets) > 1 else [states[0]]
        rises = np.array([r.misfit - state.misfit for r in reduced])
        # the held-out episodes decide, for either rule (`_shown_on_held_out`)
        shares, left = _held_out_shares(fit, state, reduced)
        now = _shown_on_held_out(shares, left)
        if first:
            shown.update(c.key for c, yes in zip(state.selected, now) if yes)
            first = False
        kept = now | np.array([c.key in shown for c in state.selected])
        small = (rises < state.misfit) & ~kept
        indistinct = _indistinct(model, state, fit.cfg.min_scale_change) & ~kept
        weak = small | indistinct
        if not weak.any():
            break
        reasons = [
            "; ".join(
                ([_misfit_reason(rises[i], state.misfit)] if small[i] else [])
                + (["its 95% interval reaches no effect"] if indistinct[i] else [])
            )
            + ", and "
            + _held_out_reason(shares[i], left)
            for i in range(len(weak))
        ]
        states = _refuse_weakest(fit, states, sets, reduced, rises, weak, refused, reasons)
    return states


def _misfit_reason(rise: float, misfit: float) -> str:
    return (
        f"without it the identification misfit rises by {rise:.3g}, less than the "
        f"{misfit:.3g} the model leaves"
    )


def _held_out_reason(share: float, left: float) -> str:
    return (
        f"without it the held-out MSE rises by {share:.3g}, less than the {left:.3g} per "
        "residual the model leaves"
    )


def _refuse_weakest(fit, states, sets, reduced, rises, weak, refused, reasons) -> list[State]:
    """Take out the weak effect whose removal raises the error least (`rises`), append the
    refused state (its effect last, `reasons` of it as `refused_because`) with the state
    without it to `refused`, and return the chain rebuilt without it."""
    state = states[-1]
    j = int(np.flatnonzero(weak)[np.argmin(rises[weak])])
    with_it = dataclasses.replace(
        state, selected=sets[j] + [state.selected[j]], refused_because=reasons[j]
    )
    refused.append((with_it, reduced[j]))
    return _chain_without(fit, states, j, reduced[j])


def _refuse_within_heldout_mismatch(
    fit,
    states: list[State],
    refused: list[tuple[State, State]],
    shown: set[str] | frozenset[str] = frozenset(),
) -> list[State]:
    """What the final model leaves of the held-out error above the measurement noise is, once
    selection has ended and the remainder has no effect of the library left in it, the named
    laws' mismatch with the plant's. An effect whose share of the held-out error (what
    dropping it, the others refitted, adds to the held-out mean squared error) is within
    that, i.e. smaller than it, is no more than that mismatch shows: a compensation for it,
    not a finding, however confident its interval. Beside MuJoCo's soft rail friction and a
    hinge damper, a cart 7% heavier [1.04, 1.10] that removes 0.2% of the error while the
    model leaves more. `_refuse_law_mismatch` judges the identification misfit, which an
    effect fitted to that very data's mismatch lowers well; held-out episodes tell whether
    the lowering carries over. The weakest is taken out, the rest refitted, until every
    effect's share is above what the model leaves (or, in `shown`, was above it beside all the
    others: `_refuse_law_mismatch`); each refused state (its effect last) is appended to
    `refused` with the state without it. Returns the rebuilt chain."""
    while states[-1].selected:
        state = states[-1]
        sets = [[c for c in state.selected if c is not out] for out in state.selected]
        reduced = fit.sets(state, sets) if len(sets) > 1 else [states[0]]
        rises, left = _held_out_shares(fit, state, reduced)
        weak = (rises < left) & np.array([c.key not in shown for c in state.selected])
        if not weak.any():
            break
        reasons = [_held_out_reason(r, left) for r in rises]
        states = _refuse_weakest(fit, states, sets, reduced, rises, weak, refused, reasons)
    return states


def _shown(fit, state: State) -> set[str]:
    """Keys of the state's effects that trade off against another (`trade_offs`) and whose
    held-out share, refitted jointly without them, is above what the model leaves
    (`_held_out_shares`)."""
    traded = trade_offs(state)
    if not traded.any():
        return set()
    sets = [[c for c in state.selected if c is not out] for out in state.selected]
    shares, left = _held_out_shares(fit, state, fit.sets(state, sets))
    shown = _shown_on_held_out(shares, left)
    return {c.key for c, t, s in zip(state.selected, traded, shown) if t and s}


def _shown_on_held_out(shares: np.ndarray, left: float) -> np.ndarray:
    """[selected] whether the held-out episodes show each effect: dropping it, the others
    refitted, raises the held-out mean squared error by at least what the model leaves above
    the noise (`_held_out_shares`). The one rule for an effect whose interval reaches its
    no-op (`_indistinct`), whether or not it trades off against another. Such an interval
    says how well the data pin the effect's value, law mismatch included: the mismatch of
    the named laws with the plant's (a Coulomb law for a Stribeck plant with backlash and a
    rough rail) widens it in proportion to what the model leaves, while the effect may
    still remove far more than that. Whether an effect is there is a comparison of two
    models on episodes neither was fitted to, and the margin it must clear is the same
    mismatch: what the effect explains beyond it cannot be a compensation for it."""
    return shares >= left


def _held_out_shares(fit, state: State, reduced: list[State]) -> tuple[np.ndarray, float]:
    """Each effect's share of the held-out error (what dropping it, the others refitted,
    adds to the held-out mean squared error), and what the model leaves above the noise: the
    identification misfit per residual (measured held-out errors carry the noise of their
    initial states, which estimated initial states keep out of the misfit)."""
    rises = np.array([r.heldout_error**2 - state.heldout_error**2 for r in reduced])
    return rises, state.misfit / max(fit.count, 1.0)


def _indistinct(model, state: State, min_scale_change: float) -> np.ndarray:
    """[selected] whether each continuous effect's 95% intervals (noise and law mismatch, as
    reported) reach its no-op value in every parameter: the nominal value, or for a scale
    (no-op 1) a change below `scale_margin`, the least `_within_mismatch` calls an effect.
    Once selection has ended the misfit is the laws' mismatch alone, so, unlike during
    selection, it belongs in the interval."""
    if state.h is None:  # no fit's curvature, no interval
        return np.zeros(len(state.selected), bool)
    half = state.half_widths()
    scales = any(model.nominal[s] == 1.0 for s in state.slots)
    scale = scale_margin(model, state, min_scale_change) if scales else 0.0

    def reaches_no_op(s: int) -> bool:
        nominal = float(model.nominal[s])
        margin = scale if nominal == 1.0 else 0.0
        # inf: the data do not determine it, judged elsewhere
        return np.isfinite(half[s]) and abs(float(state.theta[s]) - nominal) <= half[s] + margin

    return np.array(
        [bool(c.slots) and all(reaches_no_op(s) for s in c.slots) for c in state.selected]
    )


# fresh candidates a round fits again with estimated states after the held-state screen
# (`_Fitter.__call__`): the best by the screen's held-out error, and the runner-up, where
# the two rankings may differ in order (experiments/discovery_speed)
SCREENED = 2


class Batch(NamedTuple):
    """One batched fit: per row theta [C, N], delay [C, n_act], held-out error [C],
    identification MSE [C], H [C, M, M], G [C, E, M], slots [C, M], iterations [C], and H
    [C, V, M, M], G [C, V, E, M] of each view."""

    theta: np.ndarray
    delay: np.ndarray
    held: np.ndarray
    loss: np.ndarray
    h: np.ndarray
    g: np.ndarray
    slots: np.ndarray
    iterations: np.ndarray
    view_h: np.ndarray
    view_g: np.ndarray
    z: np.ndarray  # [C, W, n_obs] the windows' estimated initial states
    # [C] rows fitted with the states held at the current model's (a screen, `_Fitter`)
    screened: np.ndarray


class _Fitter:
    """Batched fits of the engine for selection: every candidate added to a state, or given
    sets of effects; always C rows (one compile per slot width), the rows a call leaves
    empty skipped."""

    def __init__(self, engine, ident, heldout, cfg, estimate, sizes, sw, floor, carried=0.0):
        self.engine, self.ident, self.heldout, self.cfg = engine, ident, heldout, cfg
        self.estimate, self.sizes, self.sw = estimate, sizes, sw
        self.workers = cpu_workers(cfg.threads)
        obs, _, _, _, mask, _ = ident
        self.count = float(np.sum(np.asarray(mask))) * engine.horizon * obs.shape[-1]
        # the squared residual per entry that noise alone leaves: estimated initial states
        # (n_obs unknowns per window of k * n_obs residuals) absorb 1/k of it; measured ones
        # carry their own error through every window (`Engine.carried_noise`)
        self.noise_mse = floor**2 * ((1.0 - 1.0 / engine.horizon) if estimate else 1.0)
        self.noise_mse += 0.0 if estimate else carried

    def misfit(self, mse: float) -> float:
        """The identification sum of squared normalized residuals above the noise."""
        return max(mse - self.noise_mse, 0.0) * self.count

    def width(self, n_slots: int) -> int:
        return next(w for w in self.sizes if w >= n_slots)

    def run(self, theta0, slots, delay, rows=None, z0=None, hold=False) -> Batch:
        engine = self.engine
        theta, loss, h, g, its, view_h, view_g, z = engine.fit(
            theta0,
            slots,
            delay,
            self.ident,
            self.cfg.iterations,
            self.estimate and not hold,
            rows,
            z0,
            True,
            hold,
            self.workers,
        )
        # (only the rows fitted: the others' are never read)
        held = engine.errors(theta, delay, self.heldout, rows)
        screened = np.full(len(theta), bool(hold))
        return Batch(theta, delay, held, loss, h, g, slots, its, view_h, view_g, z, screened)

    def __call__(self, state: State, banned=()) -> Batch:
        """Every candidate added to `state`, fitted. With initial states estimated, a
        round screens first: each candidate's fit with the windows' states held at the
        current model's (theta alone, a third of the tangents, no state blocks), then the
        rows selection decides on are fitted again with the states estimated: the best
        SCREENED candidates not yet selected (by held-out error, which measured states give
        either way; the best of them not `banned` among them), and the best refit of the
        selected ones: the rows selection compares. What a candidate adds to the dynamics
        moves the windows' states little (a round's fit starts them there for that
        reason), so the held-state fits rank the candidates as the estimated ones do; the
        held-out error of a screened row is the held-state fit's
        (experiments/discovery_speed: the two rankings on the noisy record and lab draws)."""
        model = self.engine.model
        width = self.width(len(state.slots) + self.sw)
        theta0, slots, delay = _batch(model, state, width)
        if not self.estimate:
            return self.run(theta0, slots, delay, z0=state.z)
        screen = self.run(theta0, slots, delay, z0=state.z, hold=True)
        held = np.where(np.isfinite(screen.held), screen.held, np.inf)
        chosen = np.zeros(len(theta0), bool)
        inside = [i for i, c in enumerate(model.candidates) if c.key in state.keys]
        outside = sorted(set(range(len(held))) - set(inside), key=lambda i: held[i])
        fresh = [i for i in outside if model.candidates[i].key not in banned]
        # the best refit, the best SCREENED others (a banned one among them is compared with
        # the best fresh one by `_unidentifiable_explains_more`), and the best fresh one
        chosen[sorted(inside, key=lambda i: held[i])[:1] + outside[:SCREENED] + fresh[:1]] = True
        full = self.run(theta0, slots, delay, rows=chosen, z0=state.z)

        def pick(a, b):  # the refitted row where chosen, else the screen's
            return np.where(chosen.reshape((-1,) + (1,) * (np.ndim(a) - 1)), a, b)

        return Batch(*(pick(a, b) for a, b in zip(full, screen, strict=True)))

    def state(self, selected, batch: Batch, i: int) -> State:
        slots = [int(s) for s in batch.slots[i] if s >= 0]
        m = len(slots)
        return State(
            list(selected),
            np.asarray(batch.theta[i]),
            np.asarray(batch.delay[i]),
            float(batch.held[i]),
            float(np.sqrt(batch.loss[i])),
            batch.h[i][:m, :m],
            batch.g[i][:, :m],
            slots,
            self.misfit(float(batch.loss[i])),
            (batch.view_h[i][:, :m, :m], batch.view_g[i][:, :, :m]),
            batch.z[i] if self.estimate else None,
        )

    def sets(self, state: State, sets: list[list[Candidate]]) -> list[State]:
        """Each set of effects refitted jointly from state's values: theta's, and a delay's
        length where `state` has that candidate, its candidate's own length where not (a
        delay of another length)."""
        if not sets:
            return []
        model = self.engine.model
        n_c = len(model.candidates)
        if len(sets) > n_c:  # a call fits C rows (one compiled program): more in turns
            return [
                s for k in range(0, len(sets), n_c) for s in self.sets(state, sets[k : k + n_c])
            ]
        width = self.width(max(sum(len(c.slots) for c in s) for s in sets))
        theta0 = np.tile(model.nominal, (n_c, 1))
        delay = np.zeros((n_c, len(state.delay)), np.int32)
        slots = -np.ones((n_c, width), np.int32)
        for i, chosen in enumerate(sets):
            own = [s for c in chosen for s in c.slots]
            theta0[i, own] = state.theta[own]
            slots[i, : len(own)] = own
            for c in chosen:
                if c.shifts_actions:
                    inside = c in state.selected
                    delay[i, c.actuator] = state.delay[c.actuator] if inside else c.steps
        batch = self.run(theta0, slots, delay, rows=len(sets), z0=state.z)
        return [self.state(chosen, batch, i) for i, chosen in enumerate(sets)]


INSEPARABLE = 0.95  # |correlation| above which the data do not separate two parameters


def intervals(model, state: State, delay_steps: dict | None = None) -> dict:
    """95% intervals of each selected effect's parameters, by effect key (noise and law
    mismatch: what the model fails to fit and how its fit moves between views of the data,
    see `confidence_intervals`); a delay's are the steps the data cannot rule out
    (`delay_steps`: key -> [lowest, highest], from `delay_range`)."""
    half = state.half_widths()
    out = {}
    for cand in state.selected:
        if cand.shifts_actions:
            steps = int(state.delay[cand.actuator])
            out[cand.key] = {cand.params[0]: (delay_steps or {}).get(cand.key, [steps, steps])}
            continue
        out[cand.key] = {}
        for p, s in zip(cand.params, cand.slots, strict=True):
            value, w = float(state.theta[s]), half[s]
            lo, hi = float(model.lower[s]), float(model.upper[s])
            out[cand.key][p] = [max(value - w, lo), min(value + w, hi)]
    return out


def correlations(state: State) -> list[dict]:
    """Correlations between the fitted parameters of different effects, strongest first;
    `inseparable` where the data cannot tell them apart (|rho| > INSEPARABLE)."""
    if not state.slots:
        return []
    ci = state.intervals()
    names = {s: f"{c.key}.{p}" for c in state.selected for p, s in zip(c.params, c.slots)}
    owner = {s: c.key for c in state.selected for s in c.slots}
    rows = []
    for i, a in enumerate(state.slots):
        for j in range(i + 1, len(state.slots)):
            b = state.slots[j]
            if owner[a] == owner[b]:
                continue
            rho = float(ci.corr[i, j])
            rows.append(
                {
                    "a": names[a],
                    "b": names[b],
                    "rho": rho,
                    "inseparable": bool(not np.isfinite(rho) or abs(rho) > INSEPARABLE),
                }
            )
    rows.sort(key=lambda r: -abs(r["rho"]) if np.isfinite(r["rho"]) else -2.0)
    return rows


def delay_range(engine: Engine, state: State, ident, floor: float) -> dict[str, list[int]]:
    """Per selected delay, [lowest, highest] steps the identification data cannot rule out:
    the other effects held at their values, a length whose squared error exceeds the best
    one's by no more than the model's misfit plus a 95% chi-square margin of the noise (an
    episode counted as one independent unit) stays in."""
    model = engine.model
    obs, _, _, _, mask, _ = ident
    episodes = len(np.unique(np.asarray(ident[2])[np.asarray(mask) > 0]))
    count = float(np.sum(np.asarray(mask))) * engine.horizon * obs.shape[-1]
    tolerance = state.misfit + stats.chi2.ppf(0.95, 1) * floor**2 * count / max(episodes, 1)
    out = {}
    n_c = len(model.candidates)
    for cand in state.selected:
        if not cand.shifts_actions:
            continue
        delays = np.tile(state.delay, (n_c, 1))
        lengths = np.arange(min(model.max_delay + 1, n_c))
        delays[lengths, cand.actuator] = lengths
        sse = engine.errors(np.tile(state.theta, (n_c, 1)), delays, ident)[lengths] ** 2 * count
        inside = lengths[sse - sse.min() <= tolerance]
        out[cand.key] = [int(inside.min()), int(inside.max())]
    return out
