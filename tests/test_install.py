"""hds as users install it: a non-editable wheel in a fresh venv finds its configs (shipped in
the package, hds/conf) from any directory, and Hydra's tab completion works.

The wheel's test builds and installs (`make test-install`, which CI runs after `make test`);
the completion tests are cheap and run in `make test`."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from tests.conftest import ROOT

# no PYTHONPATH: the installed package, not this checkout, must answer
ENV = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
ENV |= {"WANDB_MODE": "offline", "PIP_DISABLE_PIP_VERSION_CHECK": "1"}


def run(*args, cwd: Path, env=None):
    proc = subprocess.run(
        [str(a) for a in args], cwd=cwd, env=env or ENV, capture_output=True, text=True
    )
    assert proc.returncode == 0, f"{args}: {proc.stderr[-3000:]}"
    return proc.stdout


@pytest.fixture(scope="module")
def fresh_venv(tmp_path_factory):
    """A venv holding only the wheel of this checkout (`pip wheel`, not editable), the
    dependencies read from the project venv's site-packages (a .pth line: the project venv's
    own .pth files, its editable hds among them, are not processed), and a directory outside
    the checkout to run from."""
    tmp = tmp_path_factory.mktemp("install")
    source = tmp / "source"  # setuptools writes build/ and *.egg-info beside the sources
    source.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source / name)
    shutil.copytree(ROOT / "hds", source / "hds", ignore=shutil.ignore_patterns("__pycache__"))
    run(
        sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", tmp / "dist", source, cwd=tmp
    )
    (wheel,) = (tmp / "dist").glob("hds-*.whl")
    venv = tmp / "venv"
    run(sys.executable, "-m", "venv", "--without-pip", venv, cwd=tmp)
    python = venv / "bin" / "python"
    purelib = run(
        python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])", cwd=tmp
    )
    (Path(purelib.strip()) / "project_dependencies.pth").write_text(
        sysconfig.get_paths()["purelib"] + "\n"
    )
    run(
        sys.executable,
        "-m",
        "pip",
        "--python",
        python,
        "install",
        "--no-deps",
        "-q",
        wheel,
        cwd=tmp,
    )
    elsewhere = tmp / "elsewhere"
    elsewhere.mkdir()
    return venv, elsewhere


@pytest.mark.slow  # builds a wheel (with pip's isolated setuptools) and installs it: ~1 min
def test_the_wheel_installs_into_a_fresh_venv_and_composes_and_runs(fresh_venv):
    venv, cwd = fresh_venv
    python = venv / "bin" / "python"
    code = (
        "import hds; print(hds.__file__);"
        "cfg = hds.compose(['debug=fast', 'method=hds', 'real=delay']);"
        "print(cfg.algo.epochs, cfg.dynamics.model, cfg.real.effects[0].name)"
    )
    where, values = run(python, "-c", code, cwd=cwd).splitlines()
    assert Path(where).is_relative_to(venv) and values == "6 mlp action_delay"
    # the command line composes the package's configs, experiments and launchers too
    job = run(python, "-m", "hds.run", "debug=fast", "--cfg", "job", cwd=cwd)
    assert "epochs: 6" in job and "backend: analytic" in job
    hydra = run(
        python, "-m", "hds.run", "+experiment=optuna", "hydra/launcher=slurm", "--cfg", "hydra",
        cwd=cwd,
    )  # fmt: skip
    assert "OptunaSweeper" in hydra and "submitit_launcher.SlurmLauncher" in hydra
    # the console script, and its tab completion
    script = run(venv / "bin" / "hds-run", "--shell-completion", "install=bash", cwd=cwd)
    assert "complete -o nospace -o default -F hydra_bash_completion hds-run" in script


def test_tab_completion_installs_and_completes_keys_and_options():
    """`python -m hds.run --shell-completion install=bash` prints Hydra's bash script (it was
    refused as an unknown config key); the completion it installs queries the command."""
    script = run(sys.executable, "-m", "hds.run", "--shell-completion", "install=bash", cwd=ROOT)
    assert "hydra_bash_completion()" in script
    query = {**ENV, "PYTHONPATH": str(ROOT), "COMP_LINE": "hds-run algo.step", "COMP_POINT": "17"}
    keys = run(sys.executable, "-m", "hds.run", "-sc", "query=bash", cwd=ROOT, env=query)
    assert keys.split() == ["algo.step_size="]
    query |= {"COMP_LINE": "hds-run method=", "COMP_POINT": "15"}
    options = run(sys.executable, "-m", "hds.run", "-sc", "query=bash", cwd=ROOT, env=query)
    assert {"method=pods_cl", "method=hds", "method=oracle"} <= set(options.split())
