"""Config composition: every option and experiment composes; bad values fail before compiling."""

from __future__ import annotations

import pytest
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from tests.conftest import CONF, ROOT, make_config

# the study's configs, beside it: `make study` adds this folder to Hydra's search path
STUDY_CONF = ROOT / "experiments" / "sim2real_friction" / "conf"


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


def assert_values_landed(cfg, yaml_path, prefix: str = "") -> None:
    """Every value the YAML file states (not its defaults list, not hydra's, not an
    interpolation or a missing value) is the composed config's at the same key."""
    own = OmegaConf.to_container(OmegaConf.load(yaml_path), resolve=False)
    composed = OmegaConf.structured(cfg)
    for key, node in own.items():
        if key in ("defaults", "hydra"):
            continue
        for path, value in _leaves(node, f"{prefix}{key}"):
            if isinstance(value, str) and ("${" in value or value == "???"):
                continue
            assert OmegaConf.select(composed, path) == value, (yaml_path.name, path)


def _leaves(node, path):
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _leaves(v, f"{path}.{k}")
    else:
        yield path, node


@pytest.mark.parametrize("group", ["env", "real", "algo", "noise", "anneal", "dynamics", "logger"])
def test_every_option_composes(group):
    for option in options(group):
        overrides = [f"{group}={option}"]
        if (group, option) == ("env", "custom"):
            overrides += [
                "env.xml=pendulum.xml",
                "env.task.q_mean=[0]",
                "env.task.q_spread=[0.1]",
                "env.task.qd_spread=[0]",
                "env.task.q_target=[0]",
                "env.task.q_weight=[1]",
                "env.task.qd_weight=[0]",
            ]
        if group == "env" and not option.startswith("cartpole"):
            # the default plant's friction acts on the cart-pole's slider, which the other
            # models lack: validate() rejects it (test_bad_values_fail_at_composition)
            overrides.append("real=none")
        if (group, option) == ("real", "lab_furuta"):  # a plant of the Furuta's model only
            overrides.append("env=furuta_balance")
        cfg = make_config(*overrides)
        assert_values_landed(cfg, CONF / group / f"{option}.yaml", prefix=f"{group}.")


@pytest.mark.parametrize("experiment", options("experiment"))
def test_every_experiment_composes(experiment):
    """Each experiment with the command it names: hds.discover's or hds.run's config."""
    text = (CONF / "experiment" / f"{experiment}.yaml").read_text()
    config_name = "discover" if "python -m hds.discover" in text else "config"
    cfg = make_config(f"+experiment={experiment}", config_name=config_name)
    assert_values_landed(cfg, CONF / "experiment" / f"{experiment}.yaml")


@pytest.mark.parametrize(
    "experiment", sorted(p.stem for p in (STUDY_CONF / "experiment").glob("*.yaml"))
)
def test_every_study_experiment_composes_from_beside_its_study(experiment):
    """The study's configs compose with their folder on Hydra's search path (make study's
    --config-dir), and the user-facing experiments of hds/conf/experiment/ stay in reach of
    theirs (the swing-up study builds on swingup_sim2real)."""
    cfg = make_config(f"hydra.searchpath=[file://{STUDY_CONF}]", f"+experiment={experiment}")
    assert_values_landed(cfg, STUDY_CONF / "experiment" / f"{experiment}.yaml")
    assert not (CONF / "experiment" / f"{experiment}.yaml").exists()


LAUNCHERS = {
    "local_processes": "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher",
    "local_submitit": "hydra_plugins.hydra_submitit_launcher.submitit_launcher.LocalLauncher",
    "slurm": "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher",
}


@pytest.mark.parametrize("launcher", options("hydra/launcher"))
def test_every_launcher_composes(launcher):
    """hydra/launcher options compose onto the plugins' structured configs (a misspelt key
    fails here) and name a launcher class that imports; the SLURM one is never run in tests."""
    from hydra import compose, initialize_config_dir
    from hydra.utils import get_class
    from omegaconf import OmegaConf

    import hds.config  # noqa: F401  (registers the schemas)

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", [f"hydra/launcher={launcher}"], return_hydra_config=True)
    target = cfg.hydra.launcher._target_
    assert target == LAUNCHERS[launcher]
    assert get_class(target).__name__ == target.rsplit(".", 1)[1]
    ours = OmegaConf.load(CONF / "hydra" / "launcher" / f"{launcher}.yaml")
    for key, value in ours.items():
        if key != "defaults":
            assert cfg.hydra.launcher[key] == value, key


@pytest.mark.parametrize(
    "override, message",
    [
        ("real.friction_gap=-1", "real.friction_gap = -1.0 is out of range"),
        ("noise.decay=1.5", "noise.decay = 1.5 is out of range"),
        ("dynamics.beta=2", "dynamics.beta = 2.0 is out of range"),
        ("anneal.solved_for=0", "anneal.solved_for = 0 is out of range"),
        ("anneal.horizon_start=-5", "anneal.horizon_start = -5 is out of range"),
        ("anneal.horizon_full_at=1.5", "anneal.horizon_full_at = 1.5 is out of range"),
        (
            "env.backend=bullet",
            "choose one of ['generalized', 'spring', 'positional', 'mjx', 'analytic', 'tree']",
        ),
        ("algo.order=third", "algo.order = 'third' is not allowed"),
        ("env.task.angles=absolute", "env.task.angles = 'absolute' is not allowed"),
        ("algo.grad_window=-1", "algo.grad_window = -1 is out of range"),
        ("algo.grad_window=16", "algo.grad_window truncates closed-loop gradients only"),
        ("simulator=exact", "simulator = 'exact' is not allowed; choose one of ['nominal'"),
        ("sweep.noise_decay=[0.5]", "sweep.noise_decay sweeps the exponential schedule's decay"),
        ("sweep.step_size=[-0.5]", "sweep.step_size = [-0.5] must be non-negative"),
        ("discover.horizon=0", "discover.horizon = 0 is out of range"),
        ("vmap_runs=-1", "vmap_runs = -1 is out of range"),
        ("real.effects=[{name: ice, target: slider}]", "unknown effect 'ice'; the library has"),
        (
            "real.effects=[{name: coulomb_friction, target: slider, params: {force: -2}}]",
            "coulomb_friction.force = -2.0 is out of range",
        ),
        (
            "real.effects=[{name: coulomb_friction, target: slider, params: {mass: 2}}]",
            "has no parameter ['mass']; its parameters are ['force']",
        ),
        (
            "real.effects=[{name: action_delay, target: slide, params: {steps: 1.5}}]",
            "action_delay.steps must be an integer",
        ),
        (  # targets are checked against env.xml's names, before anything compiles
            "real.effects=[{name: coulomb_friction, target: wheel, params: {force: 1}}]",
            "real.effects: effect 'coulomb_friction' acts on a joint, and this model has no "
            "joint 'wheel'; choose one of ['slider', 'hinge']",
        ),
        (
            "env.effects=[{name: actuator_gain, target: motor, params: {gain: 2}}]",
            "env.effects: effect 'actuator_gain' acts on a actuator, and this model has no "
            "actuator 'motor'; choose one of ['slide']",
        ),
        (
            "real.effects=[{name: viscous_damping, target: hinge}, "
            "{name: viscous_damping, target: hinge}]",
            "real.effects: effect 'viscous_damping@hinge' is given twice",
        ),
        (
            "retrain=true",  # conf/discover.yaml's default plant, real=none, has no effect
            "retrain = true evaluates both policies on the plant of `real`",
        ),
        (
            "retrain=true real=brax real.friction_gap=0",  # its friction scaled to nothing
            "Give the plant the data came from, e.g. real=mujoco 'real.effects=[",
        ),
    ],
)
def test_bad_values_fail_at_composition(override, message):
    overrides = override.split(" ") if override.startswith("retrain") else [override]
    config = "discover" if "retrain" in override else "config"
    if config == "discover":
        overrides.append("data=measured.npz")
    with pytest.raises(ValueError, match=None) as err:
        make_config(*overrides, config_name=config)
    assert message in str(err.value)


def test_a_pausing_ramp_without_waiting_for_solved_is_refused():
    with pytest.raises(ValueError, match="anneal.ramp_pauses = true needs anneal.ramp_when_solv"):
        make_config("anneal.ramp_pauses=true", "anneal.ramp_when_solved=false")


def test_retrain_composes_with_a_plant_that_has_effects():
    cfg = make_config(
        "data=measured.npz",
        "retrain=true",
        "real=mujoco",
        "real.effects=[{name: coulomb_friction, target: slider, params: {force: 20}}]",
        config_name="discover",
    )
    assert cfg.retrain and cfg.real.effects[0].target == "slider"
    assert make_config("data=measured.npz", config_name="discover").real.effects == []


def test_method_presets_choose_the_groups_and_the_row_label():
    from hds.simulators import method_name

    expected = {
        "pods": ("pods", "none", "none", "nominal", "pods"),
        "pods_cl": ("pods_cl", "none", "none", "nominal", "pods_cl"),
        "hds": ("hds", "exponential", "mlp", "nominal", "hds+mlp"),
        "hds_ensemble": ("hds", "exponential", "ensemble", "nominal", "hds+ensemble"),
        "hds_residual": ("hds", "exponential", "residual", "nominal", "hds+residual"),
        "pods_cl_effects": ("pods_cl", "none", "none", "nominal", "pods_cl"),
        "pods_corrected": ("pods_cl", "none", "none", "corrected", "pods_cl+corrected"),
        "dr": ("pods_cl", "none", "none", "randomized", "pods_cl+dr"),
        "oracle": ("pods_cl", "none", "none", "real", "oracle"),
    }
    assert set(expected) == set(options("method"))
    ranges = "dr.effects=[{name: coulomb_friction, target: slider, ranges: {force: [0, 40]}}]"
    for method, want in expected.items():
        cfg = make_config(f"method={method}", *([ranges] if method == "dr" else []))
        got = (cfg.algo.name, cfg.noise.schedule, cfg.dynamics.model, cfg.simulator)
        assert (*got, method_name(cfg)) == want


@pytest.mark.parametrize(
    "override, allowed",
    [
        ("env.frictoin=1", "env has no key 'frictoin'; its keys are: name, xml, backend, "),
        ("algo.epochz=3", "did you mean 'epochs'?"),
        ("env.task.horizn=3", "env.task has no key 'horizn'; its keys are: kind, horizon, "),
        ("seedz=3", "the config has no key 'seedz'; its keys are: env, real, algo, "),
    ],
)
def test_unknown_keys_fail(override, allowed):
    with pytest.raises(ValueError) as err:
        make_config(override)
    assert override.split("=")[0].split(".")[-1] in str(err.value)
    assert allowed in str(err.value)


def test_unknown_keys_forced_in_with_plus_fail_at_validation():
    with pytest.raises(ValueError) as err:
        make_config("+env.frictoin=1")
    assert "env has no key 'frictoin'; its keys are: name, xml, backend, " in str(err.value)
    with pytest.raises(ValueError, match="real.effects.0 has no key 'strength'; its keys are"):
        make_config("+real.effects.0.strength=3")


def test_unknown_keys_of_discover_list_the_allowed_ones():
    with pytest.raises(ValueError) as err:
        make_config("data=x.npz", "discover.horizn=3", config_name="discover")
    assert "discover has no key 'horizn'" in str(err.value)
    assert "horizon, stride, warmup" in str(err.value)


def test_a_run_directory_of_an_older_hds_loads_without_its_removed_settings(tmp_path, caplog):
    from hds.config import load_config

    cfg = make_config("method=pods_cl", "algo.epochs=7")
    saved = OmegaConf.create(OmegaConf.to_container(OmegaConf.structured(cfg)))
    saved.discover.min_share = 0.1  # settings an older hds had and this one does not
    saved.retired = 1
    OmegaConf.save(saved, tmp_path / "config.yaml")
    loaded = load_config(tmp_path / "config.yaml")
    assert loaded.algo.epochs == 7 and loaded.algo.improve_in == "closed_loop"
    assert "no longer has: discover.min_share, retired" in caplog.text


def test_a_run_of_an_older_hds_is_not_another_configuration_for_its_default_settings():
    from hds.rundir import differences

    now = OmegaConf.structured(make_config("method=pods_cl"))
    before = OmegaConf.create(OmegaConf.to_container(now))
    del before["gif"]  # a setting added since, at its default
    del before.real["name"]  # one of a group's schema (real: missing until a group fills it)
    before.discover.min_share = 0.1  # a setting removed since
    assert differences(before, now) == []
    now.gif = True
    assert differences(before, now) == ["gif: (absent) -> True"]
    now.gif, now.algo.epochs = False, 7
    assert differences(before, now) == ["algo.epochs: 100 -> 7"]
    now.threads, now.discover.threads = 1, 1  # how many runs and fits at once: same results
    assert differences(before, now) == ["algo.epochs: 100 -> 7"]


def test_wrong_type_fails():
    with pytest.raises(ConfigCompositionException) as err:
        make_config("algo.epochs=many")
    assert "epochs" in str(err.value)


def test_unknown_option_lists_the_available_ones():
    with pytest.raises(ConfigCompositionException) as err:
        make_config("noise=loud")
    assert "exponential" in str(err.value)


def test_missing_custom_mjcf_is_named():
    with pytest.raises(ValueError) as err:
        make_config("env=custom")
    assert "xml" in str(err.value)


def test_a_friction_gap_sweep_refuses_what_needs_data_at_each_gap():
    for method in ("hds", "pods_corrected"):
        with pytest.raises(ValueError, match="needs data measured at each gap"):
            make_config(f"method={method}", "sweep.friction_gap=[0,1]")


def test_closed_loop_improvement_refuses_gauss_newton():
    with pytest.raises(ValueError, match="closed_loop takes first-order steps only"):
        make_config("algo=pods_gn", "algo.improve_in=closed_loop")


def test_the_command_line_s_overrides_leave_out_flags_and_their_values():
    from hds.config import cli_overrides

    argv = ["--cfg", "hydra", "-cn", "config", "method=pods_cl", "-m", "seeds=2"]
    assert cli_overrides(argv) == ["method=pods_cl", "seeds=2"]


def test_importing_the_config_leaves_the_simulator_and_the_memory_estimate_unimported():
    """The schemas, validation and composition import neither the simulator (hds.envs, MuJoCo's
    compile) nor hds.config.model (the MJCF compiled, JAX's device asked): a validation does.
    Every name used from hds.config is still there."""
    import subprocess
    import sys

    code = (
        "import sys, hds.config as c; "
        "print(sorted(m for m in ('hds.envs', 'hds.config.model') if m in sys.modules)); "
        "c.compose(['debug=fast']); print('hds.config.model' in sys.modules)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.split("\n")
    assert out[:2] == ["[]", "True"]
    import hds.config

    names = ["CONF_DIR", "SEED_MAX", "SWEEP_KEYS", "Config", "EnvConfig", "RealConfig"]
    names += ["compose", "validate", "load_config", "env_config", "cli_overrides", "run_label"]
    names += ["check_override_keys", "config_groups", "schema_of", "plant_has_effects"]
    assert all(hasattr(hds.config, n) for n in names)
    assert (hds.config.CONF_DIR / "config.yaml").is_file()


def test_importing_the_config_imports_no_jax():
    """The schemas' defaults are plain data: registering them with Hydra (on import) asks
    neither the effect library nor the simulator kinds, which import JAX and brax."""
    import subprocess
    import sys

    code = "import hds.config, sys; assert 'jax' not in sys.modules, 'jax imported'"
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True, timeout=120)


def test_discover_effects_default_is_the_effect_library_s_default_candidates():
    from hds.config.schemas import DISCOVER_EFFECTS, DiscoverConfig
    from hds.effects.library import default_candidates

    assert list(DISCOVER_EFFECTS) == default_candidates() == DiscoverConfig().effects
    assert make_config().discover.effects == default_candidates()
