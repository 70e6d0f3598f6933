"""Step 3, explain: which effects of the library account for the gap.

Greedy forward selection on held-out error. Each round fits, in one batched call, every
candidate (effect x place) together with the effects already selected, all of them refitted
jointly on the identification episodes' k-step prediction error (Levenberg-Marquardt through
the differentiable simulator; action delays by enumeration: each delay is a candidate of its
own). The candidate whose fitted model predicts the HELD-OUT episodes best is added if it
lowers their error by a meaningful margin (`stop_margin`, relative, and `min_improvement`,
absolute); otherwise selection stops. A spurious effect fitted to noise lowers the
identification error a little but not the held-out one, so with nothing missing nothing is
named.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hds.discover.fit import Engine, confidence_intervals
from hds.discover.model import Candidate


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

    @property
    def keys(self) -> set[str]:
        return {c.key for c in self.selected}


@dataclass
class Selection:
    states: list[State]  # the base model, then one state per effect added (refitted)
    rounds: list[list[dict]]  # every candidate's fit, per round
    stopped: str  # why selection ended

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
        if cand.name == "action_delay":
            delay[i, cand.actuator] = cand.steps
    return theta0, slots, delay


def candidate_params(model, cand: Candidate, theta, delay) -> dict[str, float]:
    if cand.name == "action_delay":
        return {"steps": int(delay[cand.actuator])}
    return {p: float(theta[s]) for p, s in zip(cand.params, cand.slots, strict=True)}


def forward_selection(engine: Engine, ident, heldout, cfg, estimate: bool = False) -> Selection:
    """Select effects; `ident` and `heldout` are `Data.arrays(...)` of the two episode sets;
    `estimate`: fit each window's initial state too (noisy data)."""
    model = engine.model
    sw = _slot_width(model)
    sizes = sorted(
        {b * sw for b in cfg.slot_buckets if b < cfg.max_effects} | {max(cfg.max_effects, 1) * sw}
    )
    n_act = len(model.sim.action_names)
    base_theta, base_delay = model.nominal.copy(), np.zeros(n_act, np.int32)
    state = State(
        [],
        base_theta,
        base_delay,
        float(engine.errors(base_theta[None], base_delay[None], heldout)[0]),
        float(engine.errors(base_theta[None], base_delay[None], ident)[0]),
    )
    states, rounds = [state], []
    stopped = f"reached discover.max_effects = {cfg.max_effects}"
    if not model.candidates:
        return Selection(states, rounds, "the library has no candidate for this model")
    for round_index in range(1, cfg.max_effects + 1):
        # a few sizes of the fitted set (each a compile; each slot a tangent per iteration)
        width = next(w for w in sizes if w >= len(state.slots) + sw)
        theta0, slots, delay = _batch(model, state, width)
        theta, loss, h, g, its = engine.fit(theta0, slots, delay, ident, cfg.iterations, estimate)
        held = engine.errors(theta, delay, heldout)
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
                    "iterations": int(its[i]),
                }
            )
        rounds.append(rows)
        # the selected effects refitted together (a candidate already selected adds nothing
        # new: its row is a longer refit of the current model, or another delay length)
        refits = [i for i, c in enumerate(model.candidates) if c.key in state.keys]
        if refits:
            i = min(refits, key=lambda j: held[j])
            if held[i] < state.heldout_error:
                state = _state(
                    model,
                    state.selected,
                    theta[i],
                    delay[i],
                    held[i],
                    loss[i],
                    h[i],
                    g[i],
                    slots[i],
                )
                states[-1] = state
        fresh = [i for i, c in enumerate(model.candidates) if c.key not in state.keys]
        if not fresh:
            stopped = "every candidate is selected"
            break
        best = min(fresh, key=lambda j: held[j])
        drop = state.heldout_error - held[best]
        needed = max(cfg.stop_margin * state.heldout_error, cfg.min_improvement)
        share = (state.heldout_error**2 - held[best] ** 2) / max(
            states[0].heldout_error ** 2, 1e-30
        )
        label = model.candidates[best].label
        if not drop >= needed:
            stopped = (
                f"the best remaining candidate, {label}, lowers held-out error by "
                f"{max(drop, 0.0):.3g} (normalized RMSE), less than the margin "
                f"{needed:.3g}"
            )
            break
        if not share >= cfg.min_share:
            stopped = (
                f"the best remaining candidate, {label}, explains {share:.2%} of the "
                f"original held-out error, less than discover.min_share = "
                f"{cfg.min_share:.2%}"
            )
            break
        state = _state(
            model,
            state.selected + [model.candidates[best]],
            theta[best],
            delay[best],
            held[best],
            loss[best],
            h[best],
            g[best],
            slots[best],
        )
        states.append(state)
    return Selection(states, rounds, stopped)


def _state(model, selected, theta, delay, held, loss, h, g, slots) -> State:
    slots = [int(s) for s in slots if s >= 0]
    m = len(slots)
    return State(
        list(selected),
        np.asarray(theta),
        np.asarray(delay),
        float(held),
        float(np.sqrt(loss)),
        h[:m, :m],
        g[:, :m],
        slots,
    )


def intervals(model, state: State) -> dict[str, dict[str, list[float]]]:
    """95% confidence intervals of each selected effect's parameters, by effect key."""
    half, _ = confidence_intervals(state.theta[state.slots], state.h, state.g)
    where = {s: i for i, s in enumerate(state.slots)}
    out = {}
    for cand in state.selected:
        if cand.name == "action_delay":
            steps = int(state.delay[cand.actuator])
            out[cand.key] = {"steps": [steps, steps]}  # enumerated: the best length
            continue
        out[cand.key] = {}
        for p, s in zip(cand.params, cand.slots, strict=True):
            value, w = float(state.theta[s]), float(half[where[s]])
            lo, hi = float(model.lower[s]), float(model.upper[s])
            out[cand.key][p] = [max(value - w, lo), min(value + w, hi)]
    return out
