"""The benchmarks' own set-up (bench/): what each row measures is what its label says."""

from __future__ import annotations

import pytest

from bench.common import compose
from bench.discovery import discover_config, forget_compiled
from hds.discover import fit
from hds.discover.workflow import fit_backend, with_backend


@pytest.mark.parametrize("backend", ["analytic", "generalized"])
def test_each_discovery_row_fits_on_its_own_backend(backend):
    """bench/discovery.py's row `backend` fits through that backend: the default
    discover.backend=auto would fit the generalized row on the analytic backend."""
    cfg = compose(f"env.backend={backend}")
    dcfg = discover_config(cfg, backend, stride=1)
    assert fit_backend(with_backend(cfg.env, dcfg.backend), dcfg.backend) == backend
    assert fit_backend(cfg.env, cfg.discover.backend) == "analytic"  # what auto does


def test_discovery_rows_start_without_compiled_engines():
    fit._ENGINES["a row's engine"] = object()
    forget_compiled()
    assert not fit._ENGINES


def test_the_engine_log_counts_and_times_each_entry_point_then_restores_it():
    """bench/discovery.py's EngineLog counts the Engine's host-side calls while open, and leaves
    the Engine as it found it."""
    from types import SimpleNamespace

    import numpy as np

    from bench.discovery import ENGINE_CALLS, EngineLog

    originals = {name: getattr(fit.Engine, name) for name in ENGINE_CALLS}
    engine = SimpleNamespace(predict=lambda theta, delay, data: theta * 2)
    with EngineLog() as log:
        for _ in range(3):
            out = fit.Engine.predictions(engine, np.ones(2), np.zeros(1), None)
    np.testing.assert_array_equal(out, [2.0, 2.0])
    assert (log.calls["predictions"], log.calls["fit"]) == (3, 0)
    assert log.seconds["predictions"] > 0
    assert {name: getattr(fit.Engine, name) for name in ENGINE_CALLS} == originals


def test_gpu_results_go_beside_the_cpu_ones(tmp_path, monkeypatch):
    """A GPU's benchmark run writes its own files: the committed CPU results stay as they are."""
    import bench.common as common

    cpu_json, cpu_md = common.result_files("cpu")
    gpu_json, gpu_md = common.result_files("gpu")
    assert (cpu_json.name, cpu_md.name) == ("results.json", "RESULTS.md")
    assert (gpu_json.name, gpu_md.name) == ("results-gpu.json", "RESULTS-gpu.md")
    path, md = tmp_path / gpu_json.name, tmp_path / gpu_md.name
    common.save_section("gpu", {"title": "accelerator", "skipped": "test"}, path, md)
    assert "accelerator" in md.read_text() and sorted(tmp_path.iterdir()) == sorted([path, md])


def test_regression_flops_count_what_xla_counts():
    """bench/overhead.py's regression floor counts the dense FLOPs XLA itself reports for one
    inner epoch made of a single full-batch step (its compiled program has no loop to hide
    iterations from the cost analysis)."""
    import jax
    import jax.numpy as jnp
    import optax

    from bench.overhead import forward_flops_per_row, regression_flops
    from hds.algo.regress import weighted_mse
    from hds.envs import make_env
    from hds.networks import make_policy

    env = make_env(compose("env.backend=analytic").env)
    policy = make_policy([64, 64], env.sim)
    rows = 512
    obs = jax.random.normal(jax.random.PRNGKey(0), (rows, env.sim.n_obs))
    targets, weights = jnp.zeros((rows, env.sim.n_act)), jnp.ones(rows)
    params = policy.init(jax.random.PRNGKey(1), obs[:1])
    opt = optax.sgd(1e-3)

    def one_epoch(params):
        grads = jax.grad(lambda p: weighted_mse(policy.apply, p, obs, targets, weights))(params)
        params = optax.apply_updates(params, opt.update(grads, opt.init(params))[0])
        return weighted_mse(policy.apply, params, obs, targets, weights)

    analysis = jax.jit(one_epoch).lower(params).compile().cost_analysis()
    xla = (analysis[0] if isinstance(analysis, list) else analysis)["flops"]
    initial_loss = rows * forward_flops_per_row(params)
    counted = regression_flops(params, rows, inner_epochs=1, minibatch=rows) - initial_loss
    assert counted == pytest.approx(xla, rel=0.1)


def test_the_peers_swingup_variant_is_the_swingup_experiment():
    """bench/peers.py's pods_cl_swingup trains with conf/experiment/swingup.yaml's algo and
    noise (its epochs and chunk aside, which the bench sets), so the bench measures the
    experiment experiments/cartpole_training reports."""
    from bench.peers import DEFAULT_BUDGET

    variant = compose("env=cartpole_swingup", *DEFAULT_BUDGET["variants"]["pods_cl_swingup"])
    experiment = compose("+experiment=swingup")
    for cfg in (variant, experiment):
        cfg.algo.epochs, cfg.algo.chunk = 0, 0
    assert variant.algo == experiment.algo
    assert variant.noise == experiment.noise


@pytest.mark.parametrize(
    "variant, experiment",
    [("pods_cl_horizon", "furuta_balance"), ("pods_cl_furuta_swingup", "furuta_swingup")],
)
def test_the_peers_furuta_variants_are_the_furuta_experiments(variant, experiment):
    """bench/peers.py's Furuta variants train with their conf/experiment files' algo, noise and
    anneal (epochs and chunk aside)."""
    from bench.peers import DEFAULT_BUDGET

    variant = compose(f"env={experiment}", "real=none", *DEFAULT_BUDGET["variants"][variant])
    experiment = compose(f"+experiment={experiment}")
    for cfg in (variant, experiment):
        cfg.algo.epochs, cfg.algo.chunk = 0, 0
    assert variant.algo == experiment.algo
    assert variant.noise == experiment.noise
    assert variant.anneal == experiment.anneal


def test_peers_medians_count_a_seed_that_never_reaches_the_threshold_as_never():
    """bench/peers.py's median over seeds: a method reaching the threshold with 2 of 3 seeds
    has a median time to it; with 1 of 3 it has none."""
    from bench.peers import aggregate

    def run(returns):  # a curve point every 10 s and 100 samples
        points = [[10.0 * i, 100 * i, 300 * i, r] for i, r in enumerate(returns)]
        return {"method": "m", "points": points, "final": {"mean": returns[-1]}}

    fast, slow, never = run([-9, -5, -1]), run([-9, -8, -4, -2]), run([-9, -9, -9])
    two = aggregate([fast, slow, never], threshold=-3)
    assert (two["to"], two["reached"], two["seeds"]) == ([30.0, 300.0, 900.0], 2, 3)
    assert (two["final"], two["best"]) == (-2, -2)
    assert aggregate([fast, never, never], threshold=-3)["to"] == [None, None, None]


SMALL = "algo.rollouts=8,env.task.horizon=20,algo.inner_epochs=2"


def bench_sections(tmp_path, *argv) -> dict:
    """`python -m bench.run ARGV --out DIR`: its sections, written to DIR only."""
    import json

    from bench import run
    from bench.common import result_files

    committed = [p.read_bytes() for p in result_files("cpu") if p.exists()]
    assert run.main([*argv, "--out", str(tmp_path)]) == 0
    assert [p.read_bytes() for p in result_files("cpu") if p.exists()] == committed
    sections = json.loads((tmp_path / "results.json").read_text())["sections"]
    assert not any("error" in s for s in sections.values())
    return sections


@pytest.mark.slow  # make test-slow: keeps make test under 10 min cold
def test_bench_run_writes_its_sections_where_told(tmp_path):
    """`python -m bench.run compile --out DIR` end to end on a small budget: each point a worker
    process, the results in DIR (the committed ones untouched), the warm process compiling from
    the cold one's persistent cache."""
    sets = ("compile.backends=analytic", f"compile.overrides={SMALL}", "compile.repeats=1")
    sections = bench_sections(tmp_path, "compile", *(a for s in sets for a in ("--set", s)))
    (compiled,) = sections["compile"]["data"]
    assert compiled["cache_mib"] > 0 and compiled["warm_hit"], compiled["warm_new_entries"]
    report = (tmp_path / "RESULTS.md").read_text()
    assert "cold and warm (persistent cache) compile" in report


@pytest.mark.slow  # three worker processes, each compiling a whole training: make test-slow
def test_bench_scaling_memory_grows_with_vmapped_seeds_not_looped_ones(tmp_path):
    sets = (
        "epochs=1",
        "seeds=1,2",
        "horizons=[]",
        "rollouts=[]",
        "repeats=1",
        f"overrides={SMALL}",
    )
    sections = bench_sections(
        tmp_path, "scaling", *(a for s in sets for a in ("--set", f"scaling.{s}"))
    )
    one, two, looped = sections["scaling"]["data"]
    assert [(r["seeds"], r["vmapped"]) for r in (one, two, looped)] == [(1, 1), (2, 2), (2, 1)]
    temp = [r["memory"]["temp_mib"] for r in (one, two, looped)]
    assert temp[1] > 1.5 * temp[0] and temp[2] < temp[1], temp  # a loop holds one run at a time
    assert all(r["run_s"] > 0 and len(r["repeat_run_s"]) <= 1 for r in (one, two, looped))
    assert "calls in median" in (tmp_path / "RESULTS.md").read_text()


def test_a_compile_rerun_of_one_backend_keeps_the_other_backends_rows(tmp_path):
    """`python -m bench.run compile --set compile.backends=tree` replaces the tree rows and keeps
    the analytic ones measured before, each row naming the run it comes from."""
    from bench import compilation
    from bench.common import save_section

    def entry(backend, seconds, at):
        process = {
            k: seconds for k in ("import_s", "build_s", "init_s", "trace_s", "compile_s", "run_s")
        }
        return {
            "backend": backend,
            "overrides": [],
            "measured_at": at,
            "load": [1.0, 1.0, 1.0],
            "load_after": [2.0, 2.0, 2.0],
            "cold": {**process, "process_s": 6 * seconds},
            "warm": {**process, "process_s": seconds},
            "cache_mib": 0.5,
            "warm_hit": True,
        }

    files = (tmp_path / "results.json", tmp_path / "RESULTS.md")

    def save(*entries):
        section = {**compilation.section(list(entries), []), "budget": {}, "wall_s": 1.0}
        return save_section("compile", section, *files, merge=compilation.merge)

    save(entry("analytic", 1.0, "2026-11-27 10:00 UTC"), entry("tree", 2.0, "2026-11-27 10:05 UTC"))
    stored = save(entry("tree", 3.0, "2026-11-27 11:00 UTC"))["sections"]["compile"]
    rows = {(r[0], r[1]): r for r in stored["tables"][0]["rows"]}
    assert sorted(rows) == [
        ("analytic", "cold"),
        ("analytic", "warm"),
        ("tree", "cold"),
        ("tree", "warm"),
    ]
    # process total, process CPU s (not in these entries), measured (load)
    assert rows["analytic", "warm"][-3:] == [1.0, None, "2026-11-27 10:00 UTC (load 1/2)"]
    assert rows["tree", "warm"][-3:] == [3.0, None, "2026-11-27 11:00 UTC (load 1/2)"]
    met = {
        t["target"].split(":")[0] + (" warm" if "second" in t["target"] else " cold"): t["met"]
        for t in stored["targets"]
    }
    assert met == {
        "analytic cold": True,
        "analytic warm": True,
        "tree cold": False,
        "tree warm": True,
    }
    report = files[1].read_text()
    assert "2026-11-27 10:00 UTC (load 1/2)" in report and "2026-11-27 11:00 UTC" in report
    assert "2026-11-27 10:05 UTC" not in report  # the replaced tree rows are gone
