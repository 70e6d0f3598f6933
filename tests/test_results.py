"""The typed results (hds.results): a run directory's summary.json as hds has written it since
before the types existed still loads, reads as typed rows, and is written back unchanged."""

from __future__ import annotations

import json
import math

import pytest

from hds.results import Gathered, Row, Summary

# a summary.json as `python -m hds.run` wrote it before hds.results (trimmed: two seeds, a
# further plant, a diverged row written as null and listed under non_finite)
TODAY = """{
  "name": "sim2real_friction",
  "rows": [
    {"method": "pods_cl", "plant": "coulomb_friction@slider", "seed": 0,
     "sim_return": -3.0473227500915527, "real_return": -3.8905694484710693,
     "gap": 0.8432466983795166, "gap_relative": 0.27671722608121585,
     "solved_sim": true, "solved_real": true},
    {"method": "pods_cl", "plant": "coulomb_friction@slider", "seed": 1,
     "sim_return": null, "real_return": -250.5, "gap": null, "gap_relative": null,
     "solved_sim": false, "solved_real": false}
  ],
  "rows_eval_plants": [
    {"method": "pods_cl", "plant": "brax x2", "friction_gap": 2.0, "seed": 0,
     "sim_return": -3.0, "real_return": -9.5, "gap": 6.5, "gap_relative": 2.1666666666666665,
     "solved_sim": true, "solved_real": false}
  ],
  "timing": {"pods_cl": {"compile_s": 5.3, "train_s": 29.1, "train_cpu_s": 28.0}},
  "dynamics": {},
  "discovery": {},
  "real": {"plant": "mujoco", "name": "coulomb_friction@slider", "friction_gap": 1.0,
           "effects": [{"name": "coulomb_friction", "target": "slider",
                        "params": {"force": 20.0}}]},
  "history": {"pods_cl": {"return": [[-1404.5, -4.0], [-1400.0, -4.1]]}},
  "non_finite": ["rows[1].sim_return", "rows[1].gap", "rows[1].gap_relative"]
}
"""


def test_a_summary_json_written_before_the_types_loads_typed_and_writes_back_the_same(tmp_path):
    path = tmp_path / "summary.json"
    path.write_text(TODAY)
    summary = Summary.read(path)
    first, diverged = summary.rows
    assert (first.method, first.seed, first.plant) == ("pods_cl", 0, "coulomb_friction@slider")
    assert first.real_return == -3.8905694484710693 and first.solved_sim is True
    assert first.finite() and not diverged.finite() and math.isnan(diverged.sim_return)
    assert summary.rows_eval_plants[0].friction_gap == 2.0
    assert summary.real["name"] == "coulomb_friction@slider"
    assert summary.history["pods_cl"]["return"][1] == [-1400.0, -4.1]

    summary.write(tmp_path / "again.json")
    again = (tmp_path / "again.json").read_text()
    assert json.loads(again) == json.loads(TODAY)  # NaN back to null, non_finite again
    # key order too: a row is method, settings, returns and gaps, whether solved
    assert list(json.loads(again)["rows"][0]) == list(json.loads(TODAY)["rows"][0])


def test_a_row_reads_as_its_json_mapping_for_tables_of_any_column():
    row = Row.from_json(json.loads(TODAY)["rows_eval_plants"][0])
    assert row["friction_gap"] == 2.0 and row["gap"] == 6.5 and "seed" in row
    assert dict(row) == row.to_json() and row.get("job") is None
    assert {**row, "job": "3"} == Row.from_json({**row, "job": "3"}).to_json()


def test_a_sweeps_gathered_summary_round_trips_with_each_rows_job():
    data = {"rows": [{**json.loads(TODAY)["rows"][0], "job": "0"}], "jobs": [], "failed_jobs": []}
    gathered = Gathered.from_json(data)
    assert gathered.rows[0].job == "0" and gathered.rows[0].seed == 0
    assert gathered.to_json() == data


def test_a_row_without_its_gaps_gets_them_from_its_returns():
    row = Row.from_json({"method": "pods", "seed": 2, "sim_return": -2.0, "real_return": -5.0})
    assert (row.gap, row.gap_relative, row.seed, row.solved_sim) == (3.0, 1.5, 2, None)


def test_a_row_that_hds_did_not_write_is_refused_with_its_missing_keys():
    with pytest.raises(ValueError, match="lacks real_return"):
        Row.from_json({"method": "pods", "sim_return": 1.0})
    with pytest.raises(ValueError, match="not a run's summary"):
        Summary.from_json({"rows": [], "jobs": []})
