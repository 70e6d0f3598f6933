"""The compiled core of discovery: k-step predictions, their errors, and batched
Levenberg-Marquardt fits through the differentiable simulator.

An `Engine` holds one superset `Model` and three jitted functions, each compiled once per
data layout and reused for every candidate, every round and every call:

  predict(theta, delay, data)                    -> [W, k, n_obs] k-step predictions
  losses(theta [C, N], delay [C, n_act], active [C], data)
      -> [C] mean squared normalized error (NaN on the rows not `active`: not computed)
  fit(theta0 [C, N], slots [C, M], delay [C, n_act], data, z0 [W, n_obs])
      -> theta [C, N], loss [C], H [C, M, M], G [C, E, M], iterations [C],
         view H [C, V, M, M], view G [C, V, E, M], (estimated initial states) z [C, W, n_obs]

`fit` runs C independent fits in one call, one after another: candidate c moves only the
entries `slots[c]` of theta (-1 pads), from theta0[c], with its own action delays. Each
iteration linearizes the k-step residuals (forward mode: one tangent per fitted parameter,
all windows of all identification episodes in one batch), solves the damped Gauss-Newton
system and keeps the step only if the error falls. With each window's initial state estimated
(noisy data), the states are eliminated window by window (a Schur complement), each window
keeps its state's step only where that lowers its own error and has its own damping, and a
fit stops once theta has settled (a further step would move it by a hundredth of its
standard error) rather than when the last states stop improving. It returns the Gauss-Newton matrix
H = J J^T and the per-episode gradients G[e] = J_e r_e at the optimum, from which
`confidence_intervals` builds a cluster-robust (sandwich) covariance: windows of one
episode overlap and their errors correlate, so episodes, not residuals, are the independent units.
The same two quantities restricted to each of V views (parts of the residuals: the early and
the late steps of the windows, the positions and the velocities) measure how far the fit
would move on that part alone, the law-mismatch part of the intervals.
"""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, is_dataclass

import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

from hds.discover.model import Model, build_model
from hds.utils.runtime import CompiledPrograms, program_key

TOLERANCE = 1e-4  # an accepted step that lowers the error by less than this share: converged
ABS_TOLERANCE = 1e-9  # ... or by less than this (mean squared normalized error): converged
LAMBDA0, LAMBDA_MAX = 1e-3, 1e4
# estimated states: settled when a step moves theta by less than this share of its se. Not
# 0.1: selection's later decisions compare fits of different models (a dead band's held-out
# share against the misfit left), and a stop that loose flipped one on a lab draw
SETTLED = 0.01
SLOW = 1e-3  # ... and the error falls by less than this share a step


def row_mask(rows, n: int) -> np.ndarray:
    """[n] the rows a call computes: all (None), the first `rows` (a count) or a [n] mask."""
    if rows is not None and np.ndim(rows):
        return np.asarray(rows, bool)
    return np.arange(n) < (n if rows is None else rows)


def deal_rows(active: np.ndarray, workers: int) -> list[np.ndarray]:
    """The active rows dealt out in turn into up to `workers` masks, none empty (one mask,
    `active` itself, where there is no one to share with)."""
    rows = np.flatnonzero(active)
    n = min(int(workers), len(rows))
    if n <= 1:
        return [np.asarray(active, bool)]
    masks = [np.zeros(len(active), bool) for _ in range(n)]
    for w, mask in enumerate(masks):
        mask[rows[w::n]] = True
    return masks


def _merge(masks: list[np.ndarray], outs: list[tuple]) -> tuple:
    """Each output's rows from the call that computed them (`masks`, as `deal_rows` made)."""

    def pick(mask, a, b):
        return np.where(mask.reshape((-1,) + (1,) * (np.ndim(a) - 1)), a, b)

    merged = outs[0]
    for mask, out in zip(masks[1:], outs[1:], strict=True):
        merged = tuple(pick(mask, b, a) for a, b in zip(merged, out, strict=True))
    return merged


class Engine:
    def __init__(self, model: Model, horizon: int):
        self.model, self.horizon = model, int(horizon)
        self.views = self._views()
        # a later process reads them from the program cache: tracing and lowering them was
        # about 8 of the 16 s of a second process's first discovery (experiments/discovery_speed)
        self._programs = CompiledPrograms(program_key("discovery engine", model, self.horizon))

    def predict(self, theta, delay, data):
        return self._programs("predict", self._predict, theta, delay, data)

    def losses(self, theta, delay, active, data):
        return self._programs("losses", self._losses_each, theta, delay, active, data)

    def _fit_program(self, args: tuple, estimate: bool, hold: bool):
        """The compiled fit for `args` (theta0, slots, delay, active, data, iterations, z0).
        `iterations` only bounds the while loop, so it is traced: fits of any budget share a
        program; `estimate` changes the residuals' shapes and stays static, as does `hold`."""

        def fit(theta0, slots, delay, active, data, iterations, z0):
            return self._fit_each(
                theta0, slots, delay, active, data, iterations, estimate, z0, hold
            )

        return self._programs.get(f"fit estimate={estimate} hold={hold}", fit, *args)

    def _carried(self, theta, delay, data, spread):
        return self._programs("carried", self._carried_each, theta, delay, data, spread)

    def _fit_each(
        self, theta0, slots, delay, active, data, iterations, estimate: bool, z0, hold=False
    ):
        """The candidates' fits one after another (lax.map, not vmap): a vmapped while loop
        runs every row until the slowest converges, here each row stops at its own
        convergence (a fifth of the iterations in a typical round). Rows not `active` (the
        padding of a batch that fills fewer rows) skip their fit: theta0, NaN loss, zeros.
        Every row starts its windows' initial states (`estimate`) from z0, or (`hold`)
        keeps them there."""

        m, episodes = slots.shape[1], data[0].shape[0]
        dtype = theta0.dtype

        def skipped(theta0):
            return (
                theta0,
                jnp.asarray(jnp.nan, dtype),
                jnp.zeros((1 + len(self.views), m, m), dtype),
                jnp.zeros((1 + len(self.views), episodes, m), dtype),
                jnp.asarray(0, jnp.int32),
                z0,
            )

        def row(args):
            theta0, slots, delay, active = args
            return jax.lax.cond(
                active,
                lambda: self._fit_one(theta0, slots, delay, data, iterations, estimate, z0, hold),
                lambda: skipped(theta0),
            )

        return jax.lax.map(row, (theta0, slots, delay, active))

    def _losses_each(self, theta, delay, active, data):
        """The rows' losses one after another, as `_fit_each`'s fits: a row not `active`
        (padding, or a row the caller does not need) costs nothing and reads NaN."""

        def row(args):
            theta, delay, active = args
            return jax.lax.cond(
                active,
                lambda: self._loss(theta, delay, data),
                lambda: jnp.asarray(jnp.nan, theta.dtype),
            )

        return jax.lax.map(row, (theta, delay, active))

    # -- single-candidate pieces (vmapped or mapped above) ---------------------------------

    def _predict(self, theta, delay, data):
        obs, acts, episode, start = data[:4]
        return self.model.predict(theta, delay, obs, acts, episode, start, self.horizon)

    def _residuals(self, theta, delay, data, z=None):
        return self.model.residuals(theta, delay, data, self.horizon, z)

    def _loss(self, theta, delay, data):
        r = self._residuals(theta, delay, data)
        count = jnp.maximum(data[4].sum() * r.shape[1] * r.shape[2], 1.0)
        return jnp.sum(r * r) / count

    def _fit_one(self, theta0, slots, delay, data, iterations: int, estimate: bool, z0, hold=False):
        """One candidate's fit. With `estimate`, each window's initial state is estimated
        along (multiple shooting): z [W, n_obs], its offset from the measurement in units of
        scale, with the measurement itself as one more residual (z), starting from z0.
        Noisy initial states would otherwise bias the effects that damp their consequences
        (friction, damping). The per-window unknowns are eliminated by a Schur complement,
        window by window; each window keeps its state's step where that lowers its own
        error (its own damping), so the few near a kink that overshoot do not refuse the step
        of all. Started from the states of the model a candidate is added to,
        rather than from the measurements, a fit spends its iterations on the effects: the
        states move little when one effect is added. With `hold` (and not `estimate`), the
        windows start from the states z0 and keep them: theta alone is fitted, as from
        measured states (a screen of candidates: `explain._Fitter`)."""
        model = self.model
        n_theta, n_obs, windows = model.n_theta, model.sim.n_obs, data[2].shape[0]
        m = slots.shape[0]
        valid = slots >= 0
        basis = jax.nn.one_hot(jnp.where(valid, slots, 0), n_theta) * valid[:, None]
        lower, upper = jnp.asarray(model.lower), jnp.asarray(model.upper)
        both = valid[:, None] & valid[None, :]
        n_z = n_obs if estimate else 0
        # tangent directions: the fitted entries of theta, then (estimate) each state
        # component of every window's initial state at once (windows are independent)
        t_theta = jnp.concatenate([basis, jnp.zeros((n_z, n_theta))])
        t_z = jnp.concatenate(
            [
                jnp.zeros((m, windows, n_obs)),
                jnp.broadcast_to(jnp.eye(n_obs)[:n_z, None, :], (n_z, windows, n_obs)),
            ]
        )

        def res(theta, z):
            given = z if estimate or hold else None
            return self._residuals(theta, delay, data, given).reshape(windows, -1)

        def linear_first(k, theta, z):
            """The linearization with the first k of theta's tangents (the rest zero)."""
            pick = np.r_[np.arange(k), m + np.arange(n_z)]
            r, jac = jax.vmap(lambda tt, tz: jax.jvp(res, (theta, z), (tt, tz)))(
                t_theta[pick], t_z[pick]
            )
            rest = jnp.zeros((m - k, *jac.shape[1:]), jac.dtype)
            return r[0], jnp.concatenate([jac[:k], rest]), jac[k:]

        # a tangent costs about one forward pass, and a row fits only its valid slots (a
        # prefix of `slots`; the rest pad the bucket's width): a row of one valid slot (every
        # candidate of round 1, a refit of one effect) linearizes that one, the others all m.
        # Not a branch for each count: each copy of the linearization adds about a quarter
        # of the fit program's compile (experiments/discovery_speed)
        n_valid = jnp.sum(valid)
        single = (n_valid <= 1) & jnp.all(valid[1:] == 0)

        def linear(theta, z):  # [W, R], [M, W, R], [n_z, W, R]
            if m == 1:
                return linear_first(1, theta, z)
            branches = [lambda t, s: linear_first(m, t, s), lambda t, s: linear_first(1, t, s)]
            return jax.lax.switch(single.astype(jnp.int32), branches, theta, z)

        def per_window(r, z):
            return jnp.sum(r * r, 1) + (jnp.sum(z * z, 1) if estimate else 0.0)

        def damp(a, lam):
            """a + lam diag(a), on the last two axes (floored: a flat direction still damps)."""
            d = jnp.diagonal(a, axis1=-2, axis2=-1)
            d = jnp.maximum(d, 1e-9 * jnp.max(d, axis=-1, keepdims=True) + 1e-30)
            return a + lam[..., None, None] * (d[..., :, None] * jnp.eye(a.shape[-1]))

        def reduced(r, jt, jz, z, lam, lam_z):
            """The damped normal equations for theta (damping lam), each window's initial
            state eliminated (its own damping lam_z [W]), and the back-substitution for the
            states: (S, per-window g [W, M], states(dtheta))."""
            g = jnp.einsum("mwr,wr->wm", jt, r)
            a = damp(jnp.einsum("mwr,lwr->ml", jt, jt), jnp.asarray(lam))
            if not estimate:
                return a, g, lambda dtheta: z
            azz = damp(jnp.einsum("iwr,jwr->wij", jz, jz) + jnp.eye(n_obs), lam_z)
            azt = jnp.einsum("iwr,mwr->wim", jz, jt)
            gz = jnp.einsum("iwr,wr->wi", jz, r) + z
            kinv = jnp.linalg.inv(azz)
            k_azt, k_gz = kinv @ azt, jnp.einsum("wij,wj->wi", kinv, gz)
            a = a - jnp.einsum("wim,win->mn", azt, k_azt)
            g = g - jnp.einsum("wim,wi->wm", azt, k_gz)
            return a, g, lambda dtheta: z - k_gz - jnp.einsum("wim,m->wi", k_azt, dtheta)

        def solve(a, g):
            return jnp.linalg.solve(jnp.where(both, a, jnp.eye(m)), -jnp.where(valid, g, 0.0))

        episodes = data[0].shape[0]

        # One linearization per accepted step, at the new point: it gives the next Jacobian
        # (iteration 0 linearizes at theta0). With initial states estimated, the step's
        # states are kept window by window (a window keeps its new state only where that
        # lowers its own error at the new theta), each window with its own damping: a few
        # windows near a kink (friction's) that overshoot would otherwise refuse the step of
        # all, and hold every other window and theta back.
        def body(carry):
            theta, z, r, jt, jz, lam, lam_z, it, _ = carry
            first = it == 0
            a, g, states = reduced(r, jt, jz, z, lam, lam_z)
            dtheta = solve(a, g.sum(0))
            trial = jnp.where(first, theta, jnp.clip(theta + dtheta @ basis, lower, upper))
            loss = jnp.sum(per_window(r, z)) if estimate else jnp.sum(r * r)  # as before

            def judged(trial_loss, better):
                """The step's relative gain, the next damping, and whether theta stood
                still or the gain was small (converged)."""
                gain = (loss - trial_loss) / jnp.maximum(loss, 1e-30)
                lam_new = jnp.where(
                    first, lam, jnp.where(better, jnp.maximum(lam * 0.3, 1e-9), lam * 5)
                )
                still = jnp.all(jnp.abs(trial - theta) <= 1e-7 * (jnp.abs(theta) + 1e-3))
                small = (gain < TOLERANCE) | (loss - trial_loss < ABS_TOLERANCE * r.size)
                return gain, lam_new, still, small

            def ends(better, lam_new, small, stalled):
                """Whether the fit stops after this step: converged, stalled, damped out or
                nothing to fit (the iteration cap is the loop's `cond`)."""
                converged = ~first & ((better & small) | stalled)
                return converged | (lam_new > LAMBDA_MAX) | ~jnp.any(valid)

            if estimate:
                z_step = states(dtheta)
                # (none at the start: it is linearized whatever its error)
                both_r = jax.lax.cond(
                    first,
                    lambda: jnp.zeros((2, *r.shape), r.dtype),
                    lambda: jax.vmap(res, in_axes=(None, 0))(trial, jnp.stack([z_step, z])),
                )
                moved, kept = per_window(both_r[0], z_step), per_window(both_r[1], z)
                took = moved < kept  # False for NaN
                z_trial = jnp.where(first, z, jnp.where(took[:, None], z_step, z))
                trial_loss = jnp.sum(jnp.where(took, moved, kept))
                better = first | (trial_loss < loss)  # False for NaN
                r_new, jt_new, jz_new = jax.lax.cond(
                    better, lambda: linear(trial, z_trial), lambda: (r, jt, jz)
                )
            elif hold:  # a screen: a refused step costs a forward pass, not a linearization
                z_trial, took = z, jnp.zeros(windows, bool)
                # (the first "step" is the start, whose linearization gives its residuals)
                r_t = jax.lax.cond(first, lambda: r, lambda: res(trial, z))
                trial_loss = jnp.sum(r_t * r_t)
                better = first | (trial_loss < loss)  # False for NaN
                # ... and so does the last accepted one: a screen only ranks (its H and G,
                # left at its last linearization, are never used), so the point it stops at
                # is linearized only where another step follows
                _, lam_next, still_next, small_next = judged(trial_loss, better)
                last = ends(better, lam_next, small_next, still_next) | (it >= iterations)
                r_new, jt_new, jz_new = jax.lax.cond(
                    better & ~last,
                    lambda: linear(trial, z),
                    lambda: (
                        jax.lax.cond(
                            first, lambda: res(trial, z), lambda: jnp.where(better, r_t, r)
                        ),
                        jt,
                        jz,
                    ),
                )
            else:  # the trial's linearization gives its error, and the next Jacobian if kept
                z_trial, took = z, jnp.zeros(windows, bool)
                r_t, jt_t, jz_t = linear(trial, z)
                trial_loss = jnp.sum(r_t * r_t)
                better = first | (trial_loss < loss)  # False for NaN
                r_new, jt_new, jz_new = (
                    jnp.where(better, new, old) for new, old in ((r_t, r), (jt_t, jt), (jz_t, jz))
                )
            gain, lam_next, still, small = judged(trial_loss, better)
            lam_z = jnp.where(
                first | ~better,
                lam_z,
                jnp.clip(jnp.where(took, lam_z * 0.3, lam_z * 5), 1e-9, 1e9),
            )
            if estimate:
                # with states estimated, z may still move (by less and less, window by window)
                # while theta has settled: done when a full Gauss-Newton step (states
                # following) would move each parameter by less than SETTLED of its standard
                # error, the episodes' spread of their pulls (the intervals' sandwich, centred:
                # the mean pull is the step itself). The states' remaining gains change the
                # parameters by no more than that.
                a0, g0, _ = reduced(r, jt, jz, z, 0.0, jnp.zeros(windows))
                a0 = jnp.where(both, a0, jnp.eye(m))
                # a parameter held at its bound, the step pushing past it, is settled there;
                # the others' step is taken with it fixed
                newton = solve(a0, g0.sum(0))
                at = theta[jnp.where(valid, slots, 0)]
                held = valid & (
                    ((at <= lower[slots]) & (newton < 0)) | ((at >= upper[slots]) & (newton > 0))
                )
                free = valid & ~held
                newton = jnp.where(
                    free,
                    jnp.linalg.solve(
                        jnp.where(free[:, None] & free[None, :], a0, jnp.eye(m)),
                        -jnp.where(free, g0.sum(0), 0.0),
                    ),
                    0.0,
                )
                pulls = jax.ops.segment_sum(g0, data[2], num_segments=episodes)
                part = jax.ops.segment_sum(data[4], data[2], num_segments=episodes) > 0
                n = jnp.maximum(part.sum(), 2)
                centred = jnp.where(part[:, None], pulls - pulls.sum(0) / n, 0.0)
                influence = centred @ jnp.linalg.inv(a0)
                se = jnp.sqrt(jnp.sum(influence**2, 0) * n / (n - 1))
                # (NaN where the data do not determine a parameter: that holds no fit back)
                # (the se is measured where the fit stands: while the error still falls fast,
                # the episodes' spread there is no measure of the optimum's)
                stalled = jnp.all(~free | ~(jnp.abs(newton) > SETTLED * se)) & (gain < SLOW)
            else:
                stalled = still
            lam = lam_next
            done = ends(better, lam, small, stalled)
            pick = lambda new, old: jnp.where(better, new, old)  # noqa: E731
            return (
                pick(trial, theta),
                pick(z_trial, z),
                r_new,
                jt_new,
                jz_new,
                lam,
                lam_z,
                it + 1,
                done,
            )

        def cond(carry):
            return (carry[7] < iterations + 1) & ~carry[8]

        n_res = self.horizon * n_obs
        start = (
            theta0,
            z0 if estimate or hold else jnp.zeros((windows, n_obs)),
            jnp.zeros((windows, n_res)),
            jnp.zeros((m, windows, n_res)),
            jnp.zeros((n_z, windows, n_res)),
            jnp.asarray(LAMBDA0, theta0.dtype),
            jnp.full((windows,), LAMBDA0, theta0.dtype),
            jnp.asarray(0),
            jnp.asarray(False),
        )
        theta, z, r, jt, jz, _, _, its, _ = jax.lax.while_loop(cond, body, start)
        # the Gauss-Newton matrix and the per-episode gradients at the optimum (initial
        # states profiled out), for the confidence intervals, then the same for each view
        views = jnp.asarray(np.concatenate([np.ones((1, n_res), bool), self.views]), r.dtype)

        def normal(view):
            a, g, _ = reduced(r * view, jt * view, jz * view, z, 0.0, jnp.zeros(windows))
            return a, jax.ops.segment_sum(g, data[2], num_segments=data[0].shape[0])

        if hold and not estimate:
            # a screen only ranks: its H and G (at a stale linearization) are never read
            h = jnp.zeros((len(views), m, m), r.dtype)
            per_episode = jnp.zeros((len(views), episodes, m), r.dtype)
        else:
            h, per_episode = jax.vmap(normal)(views)
        count = jnp.maximum(data[4].sum() * n_res, 1.0)
        return theta, jnp.sum(r * r) / count, h, per_episode, its - 1, z

    def _views(self) -> np.ndarray:
        """[V, k * n_obs] masks over a window's residuals (step-major): its first and
        second half of steps, its positions and its velocities. Where the model's laws are
        the plant's, a fit to any one of them has the same target; a law that differs (MuJoCo's
        soft-constraint friction against the library's tanh) is matched differently at short
        and long range, in positions and in velocities."""
        n_obs = self.model.sim.n_obs
        step = np.arange(self.horizon * n_obs) // n_obs
        position = np.arange(self.horizon * n_obs) % n_obs < self.model.sim.nq
        early = step < self.horizon // 2
        return np.stack([early, ~early, position, ~position])

    # -- host-side entry points ------------------------------------------------------------

    def fit(
        self,
        theta0,
        slots,
        delay,
        data,
        iterations: int,
        estimate: bool = False,
        rows=None,
        z0=None,
        states: bool = False,
        hold: bool = False,
        workers: int = 1,
    ):
        """The fits of `_fit_each`; only the first `rows` rows are fitted (default: all; or
        a [C] mask of the rows to fit), each from the windows' initial states z0 [W, n_obs]
        (`estimate`, or `hold`: kept there; default: the measurements). Returns theta, loss,
        H, G, iterations, then H and G of each view (zeros with `hold`: a screen only ranks),
        and with `states` the estimated initial states z [C, W, n_obs].
        With `workers` > 1 (hds.utils.runtime.cpu_workers), the rows are dealt out to that
        many calls of the one compiled program, run at once on threads (XLA releases the GIL
        while it runs): each row's fit is the same computation on the same inputs, so the
        same numbers to the last digit."""
        active = row_mask(rows, len(theta0))
        if z0 is None:
            z0 = np.zeros((np.shape(data[2])[0], self.model.sim.n_obs))
        args = (
            jnp.asarray(theta0, jnp.float32),
            jnp.asarray(slots, jnp.int32),
            jnp.asarray(delay, jnp.int32),
            jnp.asarray(active),
            data,
            jnp.asarray(iterations, jnp.int32),
            jnp.asarray(z0, jnp.float32),
        )
        # compiled here, once, before any thread calls it
        program = self._fit_program(args, bool(estimate), bool(hold and not estimate))

        def call(mask):
            return tuple(np.asarray(x) for x in program(*args[:3], jnp.asarray(mask), *args[4:]))

        masks = deal_rows(active, workers)
        if len(masks) == 1:
            theta, loss, h, g, its, z = call(masks[0])
        else:
            with ThreadPoolExecutor(len(masks), thread_name_prefix="hds-fit") as pool:
                theta, loss, h, g, its, z = _merge(masks, list(pool.map(call, masks)))
        out = (theta, loss, h[:, 0], g[:, 0], its, h[:, 1:], g[:, 1:])
        return out + ((z,) if states else ())

    def errors(self, theta, delay, data, rows=None) -> np.ndarray:
        """[C] normalized RMSE of each row of theta [C, N] with its delays [C, n_act]; with
        `rows` (`row_mask`: a count, or a [C] mask) only of those rows, NaN elsewhere. Fewer
        rows than the library's candidates are padded to that many (skipped), so one compiled
        program serves the base model, every round and the delay ranges, and a call costs the
        rows it needs."""
        rows_in = len(theta)
        need = row_mask(rows, rows_in)
        pad = max(len(self.model.candidates) - rows_in, 0)
        theta = np.concatenate([theta, np.repeat(theta[-1:], pad, axis=0)])
        delay = np.concatenate([delay, np.repeat(delay[-1:], pad, axis=0)])
        active = np.concatenate([need, np.zeros(pad, bool)])
        mse = self.losses(
            jnp.asarray(theta, jnp.float32),
            jnp.asarray(delay, jnp.int32),
            jnp.asarray(active),
            data,
        )
        return np.sqrt(np.asarray(mse, dtype=np.float64))[:rows_in]

    def carried_noise(self, theta, delay, data, spread: np.ndarray) -> float:
        """The mean squared normalized residual per entry that the error of measured initial
        states carries through the k-step windows of `data` (`Data.arrays`): a correct model
        started from a state off by dx predicts x(t) + S_t dx, S_t the simulator's sensitivity
        of the state at step t to the initial one. For independent errors of each variable, of
        std `spread` [n_obs] (in units of scale), the expected square is sum_i spread_i^2 |S_t
        e_i|^2, averaged here over every window and step (S taken by forward-mode
        differentiation at `theta`, from the measured states). A velocity de-noised offline or
        sampled late carries a smooth error that an angle started from it turns into a drift
        growing with t, the consequence a noise floor of the compared samples alone misses:
        the fits would count it as the laws' mismatch, and every effect would have to exceed
        it."""
        out = float(
            self._carried(
                jnp.asarray(theta, jnp.float32),
                jnp.asarray(delay, jnp.int32),
                data,
                jnp.asarray(spread, jnp.float32),
            )
        )
        return out if np.isfinite(out) else 0.0

    def _carried_each(self, theta, delay, data, spread):
        windows, n, k = data[2].shape[0], spread.shape[0], self.horizon

        def res(z):
            return self.model.residuals(theta, delay, data, k, z)

        def moved(tangent):  # the residuals' change along one variable's error
            _, out = jax.jvp(res, (jnp.zeros((windows, n)),), (tangent,))
            return jnp.sum(out * out)

        tangents = jnp.broadcast_to(jnp.diag(spread)[:, None, :], (n, windows, n))
        count = jnp.maximum(data[4].sum() * k * n, 1.0)
        return jnp.sum(jax.lax.map(moved, tangents)) / count

    def predictions(self, theta, delay, data) -> np.ndarray:
        return np.asarray(
            self.predict(jnp.asarray(theta, jnp.float32), jnp.asarray(delay, jnp.int32), data),
            dtype=np.float64,
        )


@dataclass
class Intervals:
    """Uncertainty of the fitted entries: `half` = t * se + bias, the half-widths of `level`
    intervals; `se` the cluster-robust standard errors; `bias` the shift the law mismatch
    can cause; `corr` [M, M] correlations (NaN where undetermined)."""

    half: np.ndarray
    se: np.ndarray
    bias: np.ndarray
    corr: np.ndarray


def confidence_intervals(
    theta: np.ndarray,
    h: np.ndarray,
    g: np.ndarray,
    misfit: float = 0.0,
    views: tuple[np.ndarray, np.ndarray] | None = None,
    level: float = 0.95,
) -> Intervals:
    """Intervals of the fitted entries (H [M, M], G [E, M] of `fit`; `views`: its view H
    [V, M, M] and view G [V, E, M]); inf where the data do not determine a parameter.

    Noise: a sandwich covariance with episodes as clusters (windows of one episode overlap,
    so episodes are the independent units), with Student-t quantiles over the episodes.

    Law mismatch: the plant's laws are not the library's (MuJoCo's friction is a soft
    constraint, its damping is integrated implicitly, its filter by Euler), which shifts the
    fit systematically; no amount of data averages that away, and the sandwich, centred on
    the fit, cannot see it. Two measures of it, added to the noise part:
    - what the model fails to fit: a misfit r_m shifts the linearized optimum by
      H^-1 J^T r_m, at most sqrt(misfit (H^-1)_jj), `misfit` being the sum of squared
      residuals above the measurement noise. It holds large mismatches; a small one hides
      in the uncertainty of the noise estimate.
    - how the fit moves between views (a Hausman comparison): if the laws were the plant's,
      the fit to each view of the residuals (early or late steps, positions or velocities)
      would have the fit's own target, and the view's linearized shift d_v would be noise
      alone, with a variance s_v^2 measured like the sandwich's (per-episode differences of
      the two fits' influence). E[d_v^2] = b_v^2 + s_v^2, so sqrt(max(d_v^2 - s_v^2, 0))
      estimates the systematic part b_v; the largest over the views is the scale of the
      law's mismatch in that parameter. A view that cannot determine the parameter is
      left out.
    What neither sees: a mismatch that moves every view's fit alike and leaves a misfit far
    below the noise (MuJoCo's implicitly integrated damping, partly absorbed by estimated
    initial states: fitted 3% high under 0.5% noise; bench/coverage.py)."""
    participated = np.any(g != 0, axis=1)  # the episodes that took part
    g = g[participated]
    n, m = len(g), len(theta)
    inv, weak = curvature_inverse(h)
    # no episode pulls on a fit the data determine: its residual is exactly zero (noise-free
    # data, an exact law), and so is the noise part of its intervals
    exact = n == 0 and not weak.all()
    inf = np.full(m, np.inf)
    if (n < 2 and not exact) or m == 0:
        return Intervals(inf, inf, inf, np.full((m, m), np.nan))
    cov = inv @ (g.T @ g * n / max(n - 1, 1)) @ inv
    se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    bias = np.sqrt(max(misfit, 0.0) * np.maximum(np.diag(inv), 0.0))
    if views is not None:
        bias = bias + _view_disagreement(inv, g, views[0], views[1][:, participated])
    se[weak] = bias[weak] = np.inf
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(se, se)
    corr[weak, :] = corr[:, weak] = np.nan
    t = stats.t.ppf(0.5 + level / 2, n - 1) if n > 1 else 0.0
    return Intervals(t * se + bias, se, bias, corr)


def curvature_inverse(h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """H's pseudo-inverse, computed at unit diagonal, and which entries the data do not
    determine (`weak`: no curvature, or a share in a direction of no curvature)."""
    d = np.sqrt(np.maximum(np.diag(h), 0.0))
    ok = d > 1e-12 * max(d.max(initial=0.0), 1e-30)
    inv, weak = np.zeros_like(h), ~ok
    if ok.any():
        hs = h[np.ix_(ok, ok)] / np.outer(d[ok], d[ok])
        w, v = np.linalg.eigh(hs)
        keep = w > 1e-8 * w.max()
        inv[np.ix_(ok, ok)] = (v[:, keep] / w[keep]) @ v[:, keep].T / np.outer(d[ok], d[ok])
        if (~keep).any():
            weak[ok] = np.abs(v[:, ~keep]).max(axis=1) > 1e-3
    return inv, weak


def _view_disagreement(inv, g, view_h, view_g) -> np.ndarray:
    """[M] the largest systematic shift of the fit to one view (see `confidence_intervals`)."""
    n = len(g)
    influence = g @ inv  # each episode's pull on the fit (H symmetric)
    out = np.zeros(len(inv))
    for hv, gv in zip(view_h, view_g, strict=True):
        inv_v, weak_v = curvature_inverse(hv)
        shift = inv_v @ gv.sum(axis=0)
        noise = np.sum((gv @ inv_v - influence) ** 2, axis=0) * n / (n - 1)
        excess = np.sqrt(np.maximum(shift**2 - noise, 0.0))
        out = np.maximum(out, np.where(weak_v, 0.0, excess))
    return out


_ENGINES: dict = {}


def config_key(env_cfg) -> str:
    if is_dataclass(env_cfg):
        return json.dumps(asdict(env_cfg), sort_keys=True, default=str)
    from omegaconf import OmegaConf

    return json.dumps(OmegaConf.to_container(env_cfg, resolve=True), sort_keys=True, default=str)


def get_engine(env_cfg, dt: float, effects, max_delay: int, warmup: int, horizon: int) -> Engine:
    """The engine for this simulator and layout, built once per process and then reused, so
    repeated discoveries (tests, sweeps) compile nothing twice."""
    key = (
        config_key(env_cfg),
        round(float(dt), 12),
        tuple(effects),
        int(max_delay),
        int(warmup),
        int(horizon),
    )
    if key not in _ENGINES:
        _ENGINES[key] = Engine(build_model(env_cfg, dt, list(effects), max_delay, warmup), horizon)
    return _ENGINES[key]
