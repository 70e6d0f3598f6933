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
