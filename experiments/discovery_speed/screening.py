"""Whether a round's held-state screen (hds.discover.explain._Fitter: every candidate fitted
with the windows' initial states held at the current model's, then only the best few fitted
again with the states estimated) ranks the candidates as the fits with estimated states do.

Runs discovery as it is (the screen decides), and in every round also fits every candidate
with the states estimated (the code before the screen), then compares the two rankings by
held-out error: the fresh candidates' (not selected, not banned) and the refits'. Records:
the noisy record of speed.py (`record`), and the lab cart-pole draws of
experiments/lab_plants/measure.py (`lab N`: draws 0 .. N-1; its results are written to
/tmp/h38f_lab/results.json, the study's own results.json is left as it is).

    PYTHONPATH=$PWD .venv/bin/python experiments/discovery_speed/screening.py record|lab [N]

Writes experiments/discovery_speed/screening_<which>.json and prints a table a round.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy import stats

from hds.discover import explain
from hds.utils.io import atomic_write_json

HERE = Path(__file__).resolve().parent
ROUNDS: list[dict] = []
_decide = explain._Fitter.__call__


def _traced(self, state, banned=()):
    batch = _decide(self, state, banned)
    if not self.estimate:
        return batch
    model = self.engine.model
    theta0, slots, delay = explain._batch(model, state, self.width(len(state.slots) + self.sw))
    screen = self.run(theta0, slots, delay, z0=state.z, hold=True)
    full = self.run(theta0, slots, delay, z0=state.z)
    labels = [c.label for c in model.candidates]
    fresh = [i for i, c in enumerate(model.candidates) if c.key not in state.keys | set(banned)]
    refit = [i for i, c in enumerate(model.candidates) if c.key in state.keys]

    def order(held, rows):
        return sorted(rows, key=lambda i: held[i] if np.isfinite(held[i]) else np.inf)

    best = order(full.held, fresh)[0]
    screen_order = order(screen.held, fresh)
    row = {
        "record": RECORD,
        "selected": sorted(state.keys),
        "best_estimated": labels[best],
        "its_screen_rank": screen_order.index(best) + 1,
        "screen_top": [labels[i] for i in screen_order[: explain.SCREENED]],
        "spearman_fresh": float(stats.spearmanr(screen.held[fresh], full.held[fresh])[0]),
        # the held-state fit's held-out error over the estimated one's, per fresh row
        "ratio_range": [
            float(np.nanmin(screen.held[fresh] / full.held[fresh])),
            float(np.nanmax(screen.held[fresh] / full.held[fresh])),
        ],
        "decided_the_same": bool(batch.held[best] == full.held[best] and not batch.screened[best]),
    }
    if refit:
        best_refit = order(full.held, refit)[0]
        row["refit_same"] = order(screen.held, refit)[0] == best_refit
    ROUNDS.append(row)
    print("screen vs estimated:", row, flush=True)
    return batch


RECORD = ""


def main() -> None:
    global RECORD
    explain._Fitter.__call__ = _traced
    which = sys.argv[1] if len(sys.argv) > 1 else "record"
    if which == "record":
        RECORD = "noisy record"
        sys.argv = [sys.argv[0], "--repeat", "1"]
        sys.path.insert(0, str(HERE))
        import speed

        speed.main()
    else:
        sys.path.insert(0, str(HERE.parent / "lab_plants"))
        import measure

        out = Path("/tmp/h38f_lab")
        out.mkdir(exist_ok=True)
        measure.HERE = out
        n = int(sys.argv[2]) if len(sys.argv) > 2 else 5
        original, draws = measure.discover, iter(range(n))

        def discover(*args, **kwargs):
            global RECORD
            RECORD = f"lab draw {next(draws)}"  # --fresh: draws 0 .. n-1 in order
            return original(*args, **kwargs)

        measure.discover = discover
        measure.main(n, True)
    atomic_write_json(HERE / f"screening_{which}.json", {"rounds": ROUNDS})
    for r in ROUNDS:
        print(
            f"{r['record']}: {r['selected']} best estimated {r['best_estimated']} (screen rank "
            f"{r['its_screen_rank']}), rho {r['spearman_fresh']:.3f}, same {r['decided_the_same']}"
        )


if __name__ == "__main__":
    main()
