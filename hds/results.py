"""The typed results of an experiment: a `Row` per method and run of the batch, and the
`Summary` of a run (what summary.json holds), the `PlantTime` a loop round's data cost. Every
writer builds them (`hds.gap.gap_rows`, `hds.experiment.run`) and every reader parses
them (`hds.report`, `hds.callbacks`, `hds.loop`, `hds.run`, `hds.logger`, `hds.story`) through
`from_json`, so a result file's keys are spelled in one place.

`to_json` writes the layout summary.json has always had (a row is one flat object: method, its
settings, returns, gaps), so run directories written before these types existed still load,
and a result that diverged (NaN, written as null by the strict JSON writer) reads back as NaN.
Nothing here imports JAX: reading a report is fast.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

from hds.utils.io import atomic_write_json, read_json

# the measured columns of a row, in their order; every other key of a row is a setting
MEASURED = ("sim_return", "real_return", "gap", "gap_relative")
SOLVED = ("solved_sim", "solved_real")


def _number(value) -> float:
    """A measured value read back: strict JSON wrote a NaN or inf as null."""
    return float("nan") if value is None else float(value)


@dataclass(frozen=True, eq=True)
class Row(Mapping):
    """One run of the batch, evaluated: the method's label, the settings that tell its run
    apart (seed, swept keys, the plant it was measured on and its friction gap: in the order
    they were given), its mean return over the evaluation episodes on the simulator it trained
    on and on the plant, the gap (sim - real) and the gap relative to |sim|; with the task's
    `solved_at`, whether it solves the task on each; `job`: the sweep job it came from (rows
    gathered from a sweep's jobs).

    A row also reads as the flat mapping summary.json stores (`row["real_return"]`,
    `row["seed"]`): the columns of tables and figures that take any key."""

    method: str
    sim_return: float
    real_return: float
    gap: float
    gap_relative: float
    settings: dict = field(default_factory=dict)
    solved_sim: bool | None = None
    solved_real: bool | None = None
    job: str | None = None

    __hash__ = None  # settings is a dict

    @property
    def seed(self) -> int | None:
        return self.settings.get("seed")

    @property
    def plant(self) -> str | None:
        return self.settings.get("plant")

    @property
    def friction_gap(self) -> float | None:
        return self.settings.get("friction_gap")

    @classmethod
    def measured(cls, method: str, sim_return: float, real_return: float, **fields) -> Row:
        """A row from its two returns: the gap (sim - real) and the gap relative to |sim|."""
        gap = sim_return - real_return
        relative = gap / max(abs(sim_return), 1e-9)
        return cls(method, sim_return, real_return, gap, relative, **fields)

    def finite(self) -> bool:
        """Whether both returns are finite numbers (not NaN or inf: a diverged rollout)."""
        return math.isfinite(self.sim_return) and math.isfinite(self.real_return)

    def to_json(self) -> dict:
        """summary.json's row: method, settings, returns and gaps, whether solved, job."""
        out = {"method": self.method, **self.settings}
        out |= {key: getattr(self, key) for key in MEASURED}
        if self.solved_sim is not None or self.solved_real is not None:
            out |= {"solved_sim": self.solved_sim, "solved_real": self.solved_real}
        if self.job is not None:
            out["job"] = self.job
        return out

    @classmethod
    def from_json(cls, data: Mapping) -> Row:
        """A row as summary.json, loop.json or a sweep's gathered summary stores it."""
        if isinstance(data, Row):
            return data
        missing = [k for k in ("method", "sim_return", "real_return") if k not in data]
        if missing:
            raise ValueError(
                f"a result row lacks {', '.join(missing)}: {dict(data)}; it was not written by "
                "hds (rerun the experiment to rewrite its summary.json)"
            )
        known = {"method", *MEASURED, *SOLVED, "job"}
        fields = {
            "settings": {k: v for k, v in data.items() if k not in known},
            "solved_sim": data.get("solved_sim"),
            "solved_real": data.get("solved_real"),
            "job": data.get("job"),
        }
        sim, real = _number(data["sim_return"]), _number(data["real_return"])
        row = cls.measured(data["method"], sim, real, **fields)
        # the gaps as written (not recomputed: the same digits), where the row has them
        gaps = {k: _number(data[k]) for k in ("gap", "gap_relative") if k in data}
        return replace(row, **gaps)

    # the flat mapping of to_json, for tables and figures over any column
    def __getitem__(self, key: str):
        return self.to_json()[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self.to_json())

    def __len__(self) -> int:
        return len(self.to_json())


def rows_from_json(rows) -> list[Row]:
    return [Row.from_json(r) for r in rows]


@dataclass(frozen=True)
class PlantTime:
    """Seconds of plant time data cost (steps x dt): the policy deployed on the plant and
    open-loop excitation. A loop round reports what it recorded and its total so far; the lab
    study states what each method needed (docs/loop.md)."""

    deployment_s: float = 0.0
    excitation_s: float = 0.0

    @property
    def total_s(self) -> float:
        return self.deployment_s + self.excitation_s

    @classmethod
    def of_round(
        cls, episodes: int, horizon: int, dt: float, deploy_episodes: int, excitation_episodes: int
    ) -> PlantTime:
        """The plant time of a round's `episodes` recorded episodes of `horizon` steps, each
        record of the round `deploy_episodes` deployed, then `excitation_episodes` excited
        (hds.data.acquire.deployed_and_excited; active excitation records more of both)."""
        per_record = deploy_episodes + excitation_episodes
        if episodes % per_record:
            raise ValueError(
                f"{episodes} episodes are no whole number of records of {deploy_episodes} "
                f"deployed and {excitation_episodes} excited: the round's data were not "
                "recorded by this loop's settings (loop.deploy_episodes, "
                "loop.excitation_episodes); record the round again"
            )
        records, seconds = episodes // per_record, horizon * dt
        return cls(records * deploy_episodes * seconds, records * excitation_episodes * seconds)

    def __add__(self, other: PlantTime) -> PlantTime:
        return PlantTime(
            self.deployment_s + other.deployment_s, self.excitation_s + other.excitation_s
        )

    def to_json(self) -> dict:
        return {
            "deployment_s": self.deployment_s,
            "excitation_s": self.excitation_s,
            "total_s": self.total_s,
        }

    @classmethod
    def from_json(cls, data: Mapping | None) -> PlantTime:
        """As to_json wrote it; a round written before plant time was reported: none."""
        data = data or {}
        return cls(float(data.get("deployment_s", 0.0)), float(data.get("excitation_s", 0.0)))


@dataclass
class Summary:
    """What a run leaves in summary.json: its name, its rows (one per method and run), the rows
    on its further plants (`eval_plants`), each method's timing and metric history
    (`{method: {metric: [n_runs][epochs]}}`), the report of its learned model and of gap
    discovery, and the plant it was evaluated on (`real`: plant, name, friction_gap, effects)."""

    name: str
    rows: list[Row]
    rows_eval_plants: list[Row] = field(default_factory=list)
    timing: dict = field(default_factory=dict)
    dynamics: dict = field(default_factory=dict)
    discovery: dict = field(default_factory=dict)
    real: dict = field(default_factory=dict)
    history: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {
            "name": self.name,
            "rows": [r.to_json() for r in self.rows],
            "rows_eval_plants": [r.to_json() for r in self.rows_eval_plants],
            "timing": self.timing,
            "dynamics": self.dynamics,
            "discovery": self.discovery,
            "real": self.real,
            "history": self.history,
        }

    @classmethod
    def from_json(cls, data: Mapping) -> Summary:
        """A run's summary.json as written today or before (keys added since are optional;
        `non_finite`, the strict writer's list of nulls, is dropped: `to_json` makes it again)."""
        if "rows" not in data or "history" not in data:
            raise ValueError(
                "not a run's summary (no rows or history): a sweep's gathered summary is read "
                "with `Gathered.from_json`"
            )
        return cls(
            name=data.get("name", ""),
            rows=rows_from_json(data["rows"]),
            rows_eval_plants=rows_from_json(data.get("rows_eval_plants", [])),
            timing=data.get("timing", {}),
            dynamics=data.get("dynamics", {}),
            discovery=data.get("discovery", {}),
            real=data.get("real", {}),
            history=data.get("history", {}),
        )

    @classmethod
    def is_run(cls, data: Mapping) -> bool:
        """Whether a summary.json's content is a run's (a sweep's gathered one has no history)."""
        return "history" in data

    def write(self, path: str | Path) -> Path:
        """Atomically, as strict JSON (a NaN becomes null, listed under `non_finite`)."""
        return atomic_write_json(path, self.to_json())

    @classmethod
    def read(cls, path: str | Path) -> Summary:
        return cls.from_json(read_json(path))


@dataclass
class Gathered:
    """A sweep's summary.json, written by its last callback: every finished job's rows, those on
    its further plants included, each with its `job`; each job's name and plant; the jobs that
    failed."""

    rows: list[Row]
    jobs: list[dict] = field(default_factory=list)
    failed_jobs: list[str] = field(default_factory=list)

    def to_json(self) -> dict:
        return {
            "rows": [r.to_json() for r in self.rows],
            "jobs": self.jobs,
            "failed_jobs": self.failed_jobs,
        }

    @classmethod
    def from_json(cls, data: Mapping) -> Gathered:
        return cls(rows_from_json(data["rows"]), data.get("jobs", []), data.get("failed_jobs", []))
