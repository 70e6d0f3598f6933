"""The real2sim2real loop (hds/loop.py): it names a hidden friction and shrinks the gap, a
killed loop resumes to the same numbers, and active excitation pushes harder (within the
actuator's range) when the data never move a joint past its friction."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from omegaconf import OmegaConf

from hds import loop, policy_store, rundir
from hds.checkpoint import Checkpoints
from hds.data import Dataset
from hds.envs import make_env
from hds.experiment import Hooks, run, run_plants
from hds.results import PlantTime
from tests.conftest import make_config

# Round 0 and one correction round, on a tiny budget: 20 N of Coulomb friction on the rail of
# the C MuJoCo plant (the default `real`).
LOOP = (
    "debug=fast",
    "logger=none",
    "seeds=2",
    "loop.rounds=1",
    "loop.deploy_episodes=6",
    "loop.excitation_episodes=10",
    "loop.epochs=3",
    "env.task.horizon=50",
    "discover.stride=2",
)


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    out = tmp_path_factory.mktemp("loop")
    return loop.run_loop(make_config(*LOOP), out, Hooks(console=False)), out


@pytest.mark.slow
def test_the_loop_names_the_friction_and_shrinks_the_gap(uninterrupted):
    rounds, out = uninterrupted
    first, second = rounds
    (found,) = second["effects"]
    assert (found["name"], found["target"]) == ("coulomb_friction", "slider")
    assert found["params"]["force"] == pytest.approx(20.0, rel=0.1)
    assert abs(second["gap"][0]) < 0.5 * abs(first["gap"][0]), (first["gap"], second["gap"])
    assert second["data_episodes"] >= 16 and first["data_episodes"] == 0
    # at this budget no policy balances: round 1, warm-started, fails and trains again afresh
    assert second["trained_afresh"] == [0, 1] and "trained_afresh" not in first
    # trained again for round 0's epochs and round 1's: debug=fast's 6 and loop.epochs=3
    afresh = Checkpoints(out / "rounds" / "1" / "afresh" / "checkpoints" / "loop1")
    assert afresh.latest() == 6 + 3
    afresh.close()
    report = json.loads((out / "loop.json").read_text())
    assert [r["round"] for r in report["rounds"]] == [0, 1]
    assert report["result_round"] == loop.result_round(rounds)
    assert (out / "rounds" / "1" / "discovery" / "report.md").is_file()
    assert (out / "plots" / "loop_rounds.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.slow
def test_a_killed_loop_resumes_to_the_same_numbers(uninterrupted, tmp_path):
    rounds, _ = uninterrupted

    def die_in_round_1(epoch, metrics):
        if metrics["method"] == "loop1":
            raise KeyboardInterrupt("killed in round 1")

    with pytest.raises(KeyboardInterrupt):
        loop.run_loop(
            make_config(*LOOP), tmp_path, Hooks(progress_fn=die_in_round_1, console=False)
        )
    resumed = loop.run_loop(make_config(*LOOP), tmp_path, Hooks(console=False))
    for a, b in zip(rounds, resumed, strict=True):
        assert a["rows"] == b["rows"]
        assert a["effects"] == b["effects"]


def test_active_excitation_pushes_harder_within_the_actuator_range():
    """80 N of rail friction: the gentle default excitation (20% of the half range, 60 N at
    the rail) never moves the cart; the loop doubles the amplitude until it does."""
    cfg = make_config(
        *LOOP, "real.friction_gap=4", "loop.deploy_episodes=2", "loop.excitation_episodes=6"
    )
    env = make_env(cfg.env)
    plant = run_plants(cfg)[0]
    from hds.algo.pods import make_train_from_config

    trainer = make_train_from_config(cfg, env)
    params = jax.vmap(trainer.init, in_axes=(0, None))(
        jax.random.split(jax.random.PRNGKey(0), 1), trainer.default_hparams
    ).policy
    data, scale, notes = loop.excite_until_identifiable(
        cfg, env, plant, params, jax.random.PRNGKey(1), []
    )
    assert scale > cfg.dynamics.excitation_scale and notes
    assert "slider moves in only" in notes[0]
    from hds.data import concatenate
    from hds.discover import identifiability

    rows = identifiability(concatenate(data), cfg.env, cfg.discover.min_motion)
    assert all(r.identifiable or r.structural for r in rows) or scale == 1.0
    actions = np.concatenate([d.actions for d in data])
    low, high = env.sim.ctrl_range[0]
    assert actions.min() >= low and actions.max() <= high
    # the plant time the round reports is the recorded data's: every record, steps x dt
    spent = loop.plant_time(cfg, concatenate(data))
    assert spent.total_s == pytest.approx(actions.shape[0] * actions.shape[1] * env.sim.dt)
    assert spent.deployment_s == pytest.approx(len(data) * 2 * cfg.env.task.horizon * env.sim.dt)


def test_the_loop_figure_shows_each_round_s_return_and_gap():
    from hds import plots

    rounds = [
        {"round": 0, "real_return": (-5.0, -6.0, -4.0), "gap": (1.0, 0.5, 1.5)},
        {"round": 1, "real_return": (-3.0, -3.5, -2.5), "gap": (0.1, 0.0, 0.2)},
    ]
    fig = plots.loop_rounds(rounds)
    returns, gaps = (ax.lines[0].get_ydata() for ax in fig.axes)
    assert list(returns) == [-5.0, -3.0] and list(gaps) == [1.0, 0.1]


def test_hds_report_gives_each_loop_round_rows_and_a_section(tmp_path):
    from omegaconf import OmegaConf

    from hds.report import build

    loop_dir, hds_dir = tmp_path / "loop" / "x4", tmp_path / "loop" / "hds_x4"
    for directory, method in ((loop_dir, "pods_cl_effects"), (hds_dir, "hds")):
        directory.mkdir(parents=True)
        cfg = make_config("real.friction_gap=4", f"method={method}")
        OmegaConf.save(OmegaConf.structured(cfg), directory / "config.yaml")

    def round_report(r, real, effects):
        rows = [
            {
                "method": f"loop{r}",
                "seed": s,
                "sim_return": -3.0,
                "real_return": real + s,
                "gap": -3.0 - real - s,
                "solved_sim": True,
                "solved_real": real + s >= -30,
            }
            for s in (0, 1)
        ]
        return {
            "round": r,
            "rows": rows,
            "real_return": [real + 0.5, real, real + 1],
            "gap": [1.0, 0.5, 1.5],
            "effects": effects,
            "data_episodes": 32 * r,
        }

    friction = {
        "name": "coulomb_friction",
        "target": "slider",
        "params": {"force": 80.7},
        "ci95": {"force": [79.0, 82.0]},
    }
    rounds = [round_report(0, -40.0, []), round_report(1, -6.0, [friction])]
    (loop_dir / "loop.json").write_text(json.dumps({"rounds": rounds}))
    hds_rounds = [round_report(0, -200.0, []), round_report(1, -8.0, [friction])]
    hds_rounds[1]["model_not_used_because"] = "k=1: 0.02 against 0.01"
    (hds_dir / "loop.json").write_text(json.dumps({"rounds": hds_rounds}))
    report = build(tmp_path).read_text()
    # each loop's rounds apart, labelled by its method: 2 runs a row, not 4
    assert "| pods_cl+loop0 | coulomb_friction@slider | 2 | -3 [-3, -3] | -39.5 [" in report
    assert "| pods_cl+loop1 | coulomb_friction@slider | 2 |" in report
    assert "| hds+mlp+loop0 | coulomb_friction@slider | 2 | -3 [-3, -3] | -200 [" in report
    assert "### Sim2real loop: loop/x4 (coulomb_friction@slider)" in report
    assert "### Sim2real loop: loop/hds_x4 (coulomb_friction@slider)" in report
    assert "| 1 | coulomb_friction@slider 80.7 [79, 82] | -5.5 [-6.0, -5.0] |" in report
    assert report.count("the learned model was not used") == 1
    assert "Round 1: the learned model was not used, predicting no better than the " in report


def test_the_report_lists_the_runs_whose_learned_model_was_not_used(tmp_path):
    from hds.report import unused_models

    for job, model in (("0", {"used": True}), ("1", {"used": False, "not_used_because": "k=1"})):
        (tmp_path / job).mkdir()
        (tmp_path / job / "summary.json").write_text(json.dumps({"dynamics": model}))
    lines = unused_models(tmp_path)
    assert lines[0].startswith("Learned models not used") and "- `1`: k=1" in lines
    assert not any(line.startswith("- `0`") for line in lines)


@pytest.mark.parametrize(
    "before, after, rose",
    [
        ([-11.6, -12.8, -10.5], [-6.2, -6.5, -5.9], True),  # clear of both intervals
        ([-209.5, -712.6, 293.6], [-8.2, -8.7, -7.8], True),  # one failing seed widened round 0
        ([-3.05, -3.11, -2.99], [-3.04, -3.10, -2.98], False),  # within both
        ([-3.05, -3.11, -2.99], [-4.0, -4.5, -3.5], False),  # worse
    ],
)
def test_the_loop_goes_on_while_the_real_return_rises_beyond_the_intervals(before, after, rose):
    assert loop.improved({"real_return": before}, {"real_return": after}) is rose


def _round(real_return, solved=()):
    """A round's report: its real return [mean, low, high] and, per seed, whether the policy
    solves the task (on the simulator, on the plant)."""
    rows = [
        {"seed": k, "solved_sim": sim, "solved_real": real} for k, (sim, real) in enumerate(solved)
    ]
    return {"real_return": real_return, "rows": rows}


@pytest.mark.parametrize(
    "solved, going_on",
    [
        ([(True, True)] * 3, False),  # every seed works on the plant: the loop has settled
        ([(True, False), (True, True), (True, True)], True),  # a gap the model still misses
        ([(False, False), (True, True), (True, True)], False),  # a failed training, not a gap
        ([], False),  # a task with no `solved_at`
    ],
)
def test_the_loop_goes_on_while_a_policy_that_solves_its_simulator_fails_on_the_plant(
    solved, going_on
):
    """With 3 seeds one failing seed hides any rise of the mean (cart-pole swing-up, lab draw
    1: -2441 [-3912, -971] -> -1852 [-4722, 1018], two of round 1's seeds failing on the plant),
    so a round whose real return did not rise beyond the intervals still records another where
    a seed's policy solves the corrected simulator and fails on the plant."""
    before = _round([-2441.4, -3912.0, -970.9])
    after = _round([-1852.2, -4722.0, 1017.5], solved)
    assert loop.goes_on(before, after) is going_on
    assert loop.plant_failures(after) == ([0] if going_on else [])
    assert loop.goes_on(before, _round([-410.0, -430.0, -390.0], solved))  # rose: goes on


@pytest.mark.parametrize(
    "returns, kept",
    [
        ([[-11.6, -12.8, -10.5]], 0),  # round 0 alone
        ([[-11.6, -12.8, -10.5], [-6.2, -6.5, -5.9]], 1),  # the last improved
        ([[-11.6, -12.8, -10.5], [-1.3, -1.5, -1.1], [-1.4, -1.9, -0.9]], 2),  # within both
        # a last round that fell beyond the intervals (a lost delay: -1.3 -> -51.6)
        ([[-11.6, -12.8, -10.5], [-1.3, -1.5, -1.1], [-51.6, -80.0, -23.2]], 1),
        # a loop that went on past a fall (a seed failing on the plant): the later rise counts
        ([[-11.6, -12.8, -10.5], [-51.6, -80.0, -23.2], [-1.3, -1.5, -1.1]], 2),
        # ... and a round beaten by one two rounds before it is not left
        ([[-1.3, -1.5, -1.1], [-3.0, -9.0, 3.0], [-6.2, -6.5, -5.9]], 0),
    ],
)
def test_the_loop_leaves_its_latest_round_that_no_other_round_beats(returns, kept):
    rounds = [{"real_return": r} for r in returns]
    assert loop.result_round(rounds) == kept


def test_a_warm_started_round_ramps_its_effects_in_at_once():
    """Round 0 trains as configured; a later round starts from a policy that solves the task,
    so its continuation begins at epoch 0 and lasts as long as configured, over loop.epochs."""
    cfg = make_config("method=pods_cl_effects", "loop.epochs=40")
    assert loop.round_config(cfg, 0) is cfg
    later = loop.round_config(cfg, 1)
    assert later.anneal.effect_ramp == pytest.approx([0.0, 0.2])  # [0.5, 0.7] shifted to 0
    assert later.algo.epochs == 40 and later.anneal.ramp_when_solved
    assert cfg.anneal.effect_ramp == [0.5, 0.7] and cfg.algo.epochs == 150  # not modified
    assert loop.round_config(make_config("method=pods_cl_effects"), 2).algo.epochs == 150


def test_a_round_from_scratch_keeps_round_0s_continuation():
    """loop.warm_start=false: each round trains from scratch, so its effects wait for the
    policy as round 0's do, over loop.epochs."""
    cfg = make_config("method=pods_cl_effects", "loop.epochs=40", "loop.warm_start=false")
    later = loop.round_config(cfg, 1)
    assert later.anneal.effect_ramp == [0.5, 0.7] and later.algo.epochs == 40


def test_a_run_trained_again_from_scratch_gets_the_loop_s_epochs_so_far():
    """A run whose warm start failed in round r trains from scratch for round 0's epochs and
    rounds 1..r's, its effects growing in once it balances (the round's continuation)."""
    cfg = make_config("method=pods_cl_effects", "loop.epochs=40")
    first, second = loop.afresh_config(cfg, 1), loop.afresh_config(cfg, 2)
    assert (first.algo.epochs, second.algo.epochs) == (150 + 40, 150 + 80)
    assert first.anneal == loop.round_config(cfg, 1).anneal
    assert first.anneal.ramp_when_solved


# --- discover.excitation = designed: the loop's rounds and the corrected simulator record
# their excitation through one function (hds.discover.design.excitation_controls)

DESIGNED = ("discover.excitation=designed", "loop.deploy_episodes=1", "loop.excitation_episodes=2")


def untrained_policy(cfg, env):
    from hds.algo.pods import make_train_from_config

    trainer = make_train_from_config(cfg, env)
    return jax.vmap(trainer.init, in_axes=(0, None))(
        jax.random.split(jax.random.PRNGKey(0), 1), trainer.default_hparams
    ).policy


def test_a_designed_round_with_nothing_to_design_records_the_random_steps(caplog):
    """discover.design_effects = [action_delay] (an integer shift: no parameter the information
    is taken of): the round's excitation falls back to the very random steps of
    discover.excitation = steps, and a warning says why."""
    steps_cfg = make_config(*LOOP, *DESIGNED[1:])
    cfg = make_config(*LOOP, *DESIGNED, "discover.design_effects=[action_delay]")
    env, plant = make_env(cfg.env), run_plants(cfg)[0]
    params, key = untrained_policy(cfg, env), jax.random.PRNGKey(3)
    expected = loop.record(steps_cfg, env, plant, params, key, 0.4)
    with caplog.at_level("WARNING", logger="hds"):
        got = loop.record(cfg, env, plant, params, key, 0.4)
    assert "designed excitation failed (discover.design_effects = ['action_delay']" in caplog.text
    np.testing.assert_array_equal(got.actions, expected.actions)
    assert got.n_episodes == 3


def test_the_corrected_simulator_designs_through_the_loop_s_function_with_its_fallback(caplog):
    """simulator=corrected with discover.excitation = designed records its data through the
    loop's function: with nothing to design, fresh random steps (not the learned model's data),
    doubled while the data cannot identify (the fallback keeps active excitation)."""
    from hds.simulators import discovery_data

    over = ("simulator=corrected", "dynamics.episodes=4", "dynamics.horizon=40")
    steps_cfg = make_config(*LOOP, *over)
    cfg = make_config(*LOOP, *over, *DESIGNED[:1], "discover.design_effects=[action_delay]")
    env, plant = make_env(cfg.env), run_plants(cfg)[0]
    model_data, steps_source = discovery_data(steps_cfg, env, plant)
    with caplog.at_level("WARNING", logger="hds"):
        data, source = discovery_data(cfg, env, plant)
    assert "designed excitation failed" in caplog.text
    assert source["excitation"] == "designed" and steps_source["excitation"] == "steps"
    assert data.n_episodes == source["episodes"] and data.n_episodes % 4 == 0
    assert not np.array_equal(data.actions[:4], model_data.actions[:4])  # recorded afresh
    half = np.abs(np.diff(env.sim.ctrl_range[0])) / 2
    assert np.abs(data.actions[:4]).max() <= source["excitation_scale"] * half + 1e-9


@pytest.mark.slow  # compiles the design's nested derivatives: minutes of CPU from a cold cache
def test_designed_excitation_in_a_round_and_in_the_corrected_simulator():
    """With friction and gain to design for, a round's excitation episodes and the corrected
    simulator's records are one designed signal (every episode the same, within the round's
    amplitude), not random steps."""
    from hds.simulators import discovery_data

    cfg = make_config(*LOOP, *DESIGNED, "env.backend=analytic")
    env, plant = make_env(cfg.env), run_plants(cfg)[0]
    params, key = untrained_policy(cfg, env), jax.random.PRNGKey(3)
    steps = loop.record(make_config(*LOOP, *DESIGNED[1:]), env, plant, params, key, 0.4)
    got = loop.record(cfg, env, plant, params, key, 0.4)
    excited = got.actions[1:]  # after the deployed episode
    np.testing.assert_array_equal(excited[0], excited[1])  # one designed signal
    assert not np.array_equal(excited, steps.actions[1:])
    low, high = env.sim.ctrl_range[0]
    middle, half = (low + high) / 2, (high - low) / 2
    assert np.abs(excited - middle).max() <= 0.4 * half + 1e-6
    assert np.abs(excited - middle).max() > 0.1 * half  # it excites

    over = ("simulator=corrected", "dynamics.episodes=2", "dynamics.horizon=50")
    data, source = discovery_data(make_config(*LOOP, *over, *DESIGNED[:1]), env, plant)
    assert source["excitation"] == "designed"
    np.testing.assert_array_equal(data.actions[0], data.actions[1])


# --- HDS's hybrid: a learned residual on top of the simulator the round trains on

HYBRID = (
    "env.backend=analytic",
    "dynamics=residual",
    "dynamics.hidden=[32,32]",
    "dynamics.epochs=100",
    "dynamics.patience=30",
    "dynamics.minibatch=64",
    "dynamics.eval_steps=[1,10]",
)


@pytest.fixture(scope="module")
def hybrid_round():
    """A round's config with dynamics=residual (HDS's hybrid), the corrected simulator it
    trains on (20 N of rail friction, as discovery names it), and the round's data recorded on
    a plant (the policy deployed, and the excitation)."""
    from hds.config import EffectConfig, env_config

    cfg = make_config(*LOOP, *HYBRID)
    friction = EffectConfig("coulomb_friction", "slider", {"force": 20.0})
    corrected_cfg = env_config(dataclasses.replace(cfg.env, effects=[friction]))
    corrected = make_env(corrected_cfg)
    params = untrained_policy(cfg, corrected)

    def recorded(plant):
        return loop.record(cfg, corrected, plant, params, jax.random.PRNGKey(1), 0.4)

    return cfg, corrected_cfg, corrected, friction, recorded


def test_the_hybrid_is_fitted_on_round_data_on_top_of_the_corrected_simulator(
    hybrid_round, tmp_path
):
    """On a plant with viscous damping beyond the corrected simulator, the round's hybrid
    predicts the held-out episodes better than the corrected simulator and is used; its base
    is that simulator's step: with zero correction, exactly the corrected step (friction
    included), not the raw simulator's."""
    from hds.config import EffectConfig
    from hds.real.brax_plant import BraxPlant

    cfg, corrected_cfg, corrected, friction, recorded = hybrid_round
    damping = EffectConfig("viscous_damping", "slider", {"coefficient": 30.0})
    plant = BraxPlant(make_env(corrected_cfg, effects=[friction, damping]))
    model, report = loop.round_model(cfg, corrected_cfg, corrected, recorded(plant), tmp_path)
    assert model is not None and report["used"] is True
    assert report["simulator_effects"] == ["coulomb_friction@slider"]
    for row in report["multistep"].values():
        assert row["model"] < row["simulator"], report["multistep"]
    zero = dataclasses.replace(
        model,
        params=jax.tree.map(jnp.zeros_like, model.params),
        norm=dataclasses.replace(model.norm, y_mean=jnp.zeros_like(model.norm.y_mean)),
    )
    obs, u = jnp.array([0.1, 0.05, 0.3, -0.2]), jnp.array([0.2])

    def step(env):
        state = env.sim.step(env.params, env.sim.init(obs[:2], obs[2:], env.params), u)
        return jnp.concatenate([state.q, state.qd])

    np.testing.assert_allclose(zero.predict(obs, u), step(corrected), atol=1e-6)
    assert not np.allclose(zero.predict(obs, u), step(make_env(cfg.env)), atol=1e-4)


@pytest.mark.slow  # a second fit (~20 s on 2 busy cores)
def test_the_hybrid_is_refused_where_it_predicts_no_better_than_the_corrected_simulator(
    hybrid_round, tmp_path
):
    """On a plant that is the corrected simulator nothing is left to learn: the round's hybrid
    predicts the held-out episodes no better than the corrected simulator, and is not used
    (round.json and the log say why). The raw simulator, without the friction, it would beat."""
    from hds.real.brax_plant import BraxPlant

    cfg, corrected_cfg, corrected, _, recorded = hybrid_round
    data = recorded(BraxPlant(corrected))
    model, report = loop.round_model(cfg, corrected_cfg, corrected, data, tmp_path)
    assert model is None and report["used"] is False
    assert "model against simulator, k=1:" in report["not_used_because"]


def test_each_round_reports_the_plant_time_its_recorded_data_cost():
    """Plant time is steps x dt of the data a round recorded, split into the policy's deployed
    episodes and the excitation; active excitation's further records count too."""
    cfg = make_config(*LOOP)
    dt, horizon = 0.04, 50
    one = 6 + 10  # loop.deploy_episodes + loop.excitation_episodes of LOOP
    for records in (1, 3):
        data = Dataset(
            np.zeros((records * one, horizon + 1, 4)), np.zeros((records * one, horizon, 1)), dt
        )
        spent = loop.plant_time(cfg, data)
        assert spent.total_s == pytest.approx(data.actions.shape[0] * data.actions.shape[1] * dt)
        assert spent.deployment_s == pytest.approx(records * 6 * horizon * dt)
        assert spent.excitation_s == pytest.approx(records * 10 * horizon * dt)
    total = loop.plant_time(cfg, data) + loop.plant_time(cfg, data)
    assert PlantTime.from_json(total.to_json()) == total and total.total_s == pytest.approx(
        2 * 3 * one * 2.0
    )
    with pytest.raises(ValueError, match="no whole number of records"):
        loop.plant_time(cfg, Dataset(np.zeros((5, 3, 4)), np.zeros((5, 2, 1)), dt))


# --- loop.start_from: round 0 restored from a finished run of its training ----------------------
ROUND_0 = (*LOOP, "loop.rounds=0")
# a randomized simulator's run has its ranges (its config is refused without)
DR_FRICTION = {"name": "coulomb_friction", "target": "slider", "ranges": {"force": [0.0, 80.0]}}


def recorded_run(directory, recorded, finished=True):
    """A run directory as hds.run leaves it, without its training: config.yaml (the composed
    config rundir.claim records), summary.json when finished, the checkpoints' folder."""
    directory.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(recorded, directory / rundir.CONFIG, resolve=True)
    (directory / "checkpoints" / recorded.algo.name).mkdir(parents=True, exist_ok=True)
    if finished:
        (directory / "summary.json").write_text("{}")
    return directory


def test_round_0_started_from_a_finished_run_restores_its_policies_untrained(tmp_path):
    """A loop started from an hds.run of its training trains no epoch in round 0 and has the
    rows and policies of a loop that trains round 0 itself, which are the run's policies."""
    cfg = make_config(*ROUND_0)
    ran = tmp_path / "run"
    run(cfg, ran, Hooks(console=False))
    OmegaConf.save(OmegaConf.structured(cfg), ran / rundir.CONFIG, resolve=True)
    started_cfg = make_config(*ROUND_0, f"loop.start_from={ran}")
    assert loop.round_zero_source(started_cfg) == ran / "checkpoints" / cfg.algo.name

    epochs = []
    hooks = Hooks(progress_fn=lambda epoch, metrics: epochs.append(epoch), console=False)
    (started,) = loop.run_loop(started_cfg, tmp_path / "started", hooks)
    assert epochs == []  # restored, not trained
    (trained,) = loop.run_loop(cfg, tmp_path / "trained", Hooks(console=False))
    assert started["rows"] == trained["rows"]
    policies = [
        policy_store.load(d)[1]
        for d in (
            ran / "policies" / cfg.algo.name,
            tmp_path / "started" / "rounds" / "0" / "policies" / "loop0",
            tmp_path / "trained" / "rounds" / "0" / "policies" / "loop0",
        )
    ]
    for other in policies[1:]:
        jax.tree.map(np.testing.assert_array_equal, policies[0], other)


def test_round_0_starts_from_a_run_that_differs_in_its_evaluation_and_model_only(tmp_path):
    """The plant, the evaluation, the later rounds and the learned model (fitted from round 1)
    are no part of round 0's training: a run that differs in them is accepted."""
    theirs = make_config(*ROUND_0, "real.friction_gap=0.5", "eval_episodes=3", "name=other")
    ran = recorded_run(tmp_path / "run", OmegaConf.structured(theirs))
    ours = make_config(*LOOP, "dynamics=residual", f"loop.start_from={ran}")
    assert loop.round_zero_source(ours) == ran / "checkpoints" / "pods"


@pytest.mark.parametrize(
    "change, says",
    [
        ({"algo.epochs": 7}, "trained with other settings than this loop's round 0 (algo.epochs:"),
        ({"seed": 3}, "(seed: 3 -> 0)"),
        (
            {"simulator": "randomized", "dr.effects": [DR_FRICTION]},
            "trained on the randomized simulator; round 0 trains",
        ),
        ({"dynamics.model": "mlp", "dynamics.beta": 0.5}, "the nominal simulator and a learned"),
        (None, "holds no finished run"),
    ],
)
def test_round_0_refuses_a_run_of_another_training_in_one_line(tmp_path, change, says):
    recorded = OmegaConf.structured(make_config(*ROUND_0))
    for key, value in (change or {}).items():
        OmegaConf.update(recorded, key, value)
    ran = recorded_run(tmp_path / "run", recorded, finished=change is not None)
    ours = make_config(*ROUND_0, f"loop.start_from={ran}")
    with pytest.raises(ValueError, match="^loop.start_from: ") as err:
        loop.round_zero_source(ours)
    assert says in str(err.value) and "\n" not in str(err.value)
