"""Steps 5 and 6, add and show: the corrected model as a config `python -m hds.run` accepts as
it is and as an MJCF with the MuJoCo-native equivalents, and the report (report.md for a
person, report.html: the same as one self-contained page, report.json for a program,
plots/*.png)."""

from __future__ import annotations

import json
from dataclasses import asdict, is_dataclass
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from hds.discover import plots
from hds.discover.sysid import write_handoff
from hds.discover.workflow import Discovery
from hds.plots import save as save_figure
from hds.utils.html import markdown_page
from hds.utils.io import atomic_write_bytes, atomic_write_json


def _container(env_cfg) -> dict:
    if is_dataclass(env_cfg):
        return json.loads(json.dumps(asdict(env_cfg), default=str))
    return OmegaConf.to_container(env_cfg, resolve=True)


def corrected_env(env_cfg, result: Discovery) -> dict:
    """The env config of the corrected simulator: the original with the named effects and the
    force terms beyond the library added."""
    env = _container(env_cfg)
    env["name"] = f"{env['name']}_corrected"
    env["effects"] = [dict(e, params=dict(e["params"])) for e in result.corrected_effects]
    return env


def write_config(env_cfg, result: Discovery, out_dir: Path) -> Path:
    """out_dir/conf/env/<name>_corrected.yaml: an `env` option for `python -m hds.run
    --config-dir <out_dir>/conf env=<name>_corrected`."""
    env = corrected_env(env_cfg, result)
    path = Path(out_dir) / "conf" / "env" / f"{env['name']}.yaml"
    header = (
        "# The simulator corrected by gap discovery (hds.discover): the original env with "
        "the named effects\n# (and joint_force_terms: the force terms beyond the library).\n"
        "# Use it with: python -m hds.run --config-dir "
        f"{path.parent.parent} env={env['name']}\n"
    )
    atomic_write_bytes(path, (header + OmegaConf.to_yaml(OmegaConf.create(env))).encode())
    return path


def write_mjcf(env_cfg, result: Discovery, out_dir: Path) -> Path:
    """out_dir/corrected.xml: the MJCF with the MuJoCo-native equivalents of the effects."""
    from hds.real.mujoco_plant import mjcf_text

    text = mjcf_text(env_cfg, result.corrected_effects, source="Corrected by hds.discover")
    path = Path(out_dir) / "corrected.xml"
    atomic_write_bytes(path, text.encode())
    return path


def write_plots(result: Discovery, out_dir: Path, plot_episodes: int, bins: int) -> dict[str, Path]:
    data = result.data
    out = {}
    figs = {"locate": plots.locate(result.location, bins)}
    for name in result.before:
        figs[f"errors_{name}"] = plots.errors(
            result.error("before", name),
            result.error("after", name),
            data.obs_names,
            data.scale,
            name,
        )
    obs = np.asarray(data.obs, dtype=np.float64)
    for name in ("heldout", "validation"):
        if name not in result.before:
            continue
        episodes = data.windows[name].episodes[:plot_episodes]
        if len(episodes):
            figs[f"trajectories_{name}"] = plots.trajectories(
                obs,
                data.dt,
                result.before[name][0],
                result.after[name][0],
                episodes,
                data.obs_names,
                data.horizon,
                name,
            )
    if (matrix := plots.correlation_matrix(result.correlations)) is not None:
        figs["correlations"] = matrix
    if result.selection.rounds:
        figs["candidates"] = plots.candidates(
            result.selection.rounds[0],
            result.selection.states[0].heldout_error,
            {f"{e.name}@{e.target}" for e in result.missing_effects},
        )
    import matplotlib.pyplot as plt

    for name, fig in figs.items():
        out[name] = save_figure(fig, Path(out_dir) / "plots" / f"{name}.png")
        plt.close(fig)
    return out


def _selection_notes(result: Discovery, files: dict | None = None) -> list[str]:
    """Law mismatch, dropped proxies, correlations and what the data cannot identify."""
    lines = []
    if result.law_mismatch:
        lines += ["", "Law mismatch (not added: the named laws are not exactly the plant's):"]
        for e in result.law_mismatch:
            why = f": {e.reason}" if e.reason else ""
            lines.append(f"- `{e.name}` on {e.target} ({e.explained_fraction:.2%}){why}")
    if result.selection.dropped:
        keys = ", ".join(f"`{c.key}`" for c in result.selection.dropped)
        lines += ["", f"Dropped once a later effect made them redundant (proxies): {keys}."]
    if result.correlations:
        lines += [
            "",
            "| parameter | parameter | correlation | separable |",
            "| --- | --- | --- | --- |",
        ]
        for r in result.correlations:
            # a named pair beyond INSEPARABLE stood apart jointly (workflow._separable_count)
            sep = "only jointly" if r["inseparable"] else "yes"
            lines.append(f"| {r['a']} | {r['b']} | {_fmt(r['rho'])} | {sep} |")
        if "correlations" in (files or {}):
            lines += ["", f"![correlations](plots/{files['correlations'].name})"]
    blind = [r for r in result.identifiability if not r.identifiable]
    if blind:
        lines += ["", "Not identifiable from these data (not fitted, never named):"]
        for r in blind:
            what = r.excitation.get("why", "")
            if "amplitude" in r.excitation:
                what += (
                    f": drive {r.excitation['actuator']} up to +-{_fmt(r.excitation['amplitude'])}"
                    f" (+-{_fmt(r.excitation['amplitude_at_joint'])} N or N m; these data: "
                    f"+-{_fmt(r.excitation['used_amplitude'])}), frequencies "
                    f"{_fmt(r.excitation['frequencies_hz'][0])} to "
                    f"{_fmt(r.excitation['frequencies_hz'][1])} Hz"
                )
            lines.append(f"- `{r.key}`: {r.reason}. To identify it: {what}.")
    return lines


def _terms_section(result: Discovery) -> list[str]:
    """The sparse force terms beyond the library, added to the corrected model."""
    if not result.terms:
        return []
    before = result.error("before").normalized
    named, terms = result.error("after").normalized, result.after_terms["heldout"][1].normalized
    lines = [
        "## Terms beyond the library",
        "",
        "Sparse terms of each joint's missing force, added to the corrected model as "
        f"`joint_force_terms` (held-out k-step error, normalized RMSE: {_fmt(before)} as "
        f"it is, {_fmt(named)} with the named effects, {_fmt(terms)} with the terms too):",
        "",
        "| joint | term | coefficient | reading | share of its missing force |",
        "| --- | --- | --- | --- | --- |",
    ]
    for t in result.terms:
        lines.append(
            f"| {t.joint} | {t.term} | {_fmt(t.coefficient)} {t.unit} | {t.reading} | "
            f"{t.share:.1%} |"
        )
    if result.angle_readings:  # which reading of each hinge's angle the fit took
        lines += ["", "Hinge angles:", ""]
        lines += [f"- {r.describe()}" for r in result.angle_readings]
    return lines + [""]


def _fmt(x: float) -> str:
    return f"{x:.4g}" if np.isfinite(x) else "inf"


def markdown(
    result: Discovery,
    files: dict,
    config_path: Path,
    mjcf_path: Path,
    out_dir: Path,
    retrain: dict | None = None,
    data_name: str = "",
) -> str:
    data = result.data
    names = list(data.obs_names)
    lines = ["# Gap discovery report", ""]
    if data_name:
        lines += [
            f"Data: `{data_name}`, {len(data.windows['identification'].episodes)} "
            f"identification and {len(data.windows['heldout'].episodes)} held-out "
            f"episodes, dt = {data.dt:g} s, k = {data.horizon} steps "
            f"({data.horizon * data.dt:g} s).",
            "",
        ]
    lines += ["## Missing effects", ""]
    if result.missing_effects:
        lines += [
            "| effect | where | parameters (95% CI) | share of the gap explained |",
            "| --- | --- | --- | --- |",
        ]
        for e in result.missing_effects:
            params = "; ".join(
                f"{p} = {_fmt(v)} {e.units.get(p, '')} [{_fmt(e.ci95[p][0])}, {_fmt(e.ci95[p][1])}]"
                if p in e.ci95
                else f"{p} = {_fmt(v)} {e.units.get(p, '')}"
                for p, v in e.params.items()
            )
            if e.at_joint:
                params += (
                    " ("
                    + "; ".join(f"{_fmt(v)} N or N m at the joint" for v in e.at_joint.values())
                    + ")"
                )
            lines.append(
                f"| {e.physical_name} (`{e.name}`) | {e.target} | {params} | "
                f"{e.explained_fraction:.1%} |"
            )
    elif result.no_gap:
        lines.append(
            f"None: the simulator already predicts the held-out data to "
            f"{result.selection.states[0].heldout_error:.2g} signal stds (normalized "
            "RMSE): there is no gap to explain."
        )
    else:
        lines.append(
            "None: no effect of the library lowers the held-out error by a meaningful margin."
        )
    if result.tentative:
        lines += [
            "",
            "Tentative (they lower the error, but less than the structured remainder "
            "no effect of the library explains: likely compensations, not findings):",
        ]
        for e in result.tentative:
            params = ", ".join(f"{p} = {_fmt(v)} {e.units.get(p, '')}" for p, v in e.params.items())
            lines.append(
                f"- {e.physical_name} (`{e.name}`) on {e.target}: {params} "
                f"({e.explained_fraction:.1%})"
            )
    lines += _selection_notes(result, files)
    noise = result.noise_floor
    terms = " and the force terms" if result.terms else ""
    unknown = result.remainder_fraction - result.noise_fraction
    lines += [
        "",
        f"Unexplained: {result.unexplained_fraction:.1%} of the held-out k-step "
        f"prediction error (MSE) remains after the named effects; features explain "
        f"{result.structured_unexplained:.1%} of the original error in that remainder. "
        f"The corrected model (the named effects{terms}) leaves "
        f"{result.remainder_fraction:.1%}, of which measurement noise accounts for "
        f"{result.noise_fraction:.1%}: the other {unknown:.1%} "
        "is what no effect of the library and no force term explains. "
        f"Estimated measurement noise: {noise:.3g} signal stds (normalized RMSE floor); "
        f"initial states of the fits: {result.initial_state}; physics backend of the "
        f"fits: {result.backend}.",
        f"Selection stopped: {result.stopped}.",
        "",
    ]
    for w in result.warnings:
        lines += [f"> **Warning**: {w}", ""]
    lines += _terms_section(result)
    lines += [
        "## Error before and after",
        "",
        "RMSE per state variable, one step and over k-step rollouts from measured states.",
        "",
        "| set | variable | one-step before | one-step after | k-step before | k-step after |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for s in result.before:
        b, a = result.error("before", s), result.error("after", s)
        for i, n in enumerate(names):
            lines.append(
                f"| {s} | {n} | {_fmt(b.one_step_rmse[i])} | "
                f"{_fmt(a.one_step_rmse[i])} | {_fmt(b.rollout_rmse[i])} | "
                f"{_fmt(a.rollout_rmse[i])} |"
            )
        lines.append(
            f"| {s} | all (normalized) | | | {_fmt(b.normalized)} | {_fmt(a.normalized)} |"
        )
    lines += [""]
    for key in (
        "errors_heldout",
        "trajectories_heldout",
        "errors_validation",
        "trajectories_validation",
    ):
        if key in files:
            lines += [f"![{key}](plots/{files[key].name})", ""]
    lines += [
        "## Where the simulator and the data disagree",
        "",
        "Share of each variable's one-step residual explained by a feature (eta^2), "
        "weighted by the variable's share of the total residual:",
        "",
        "| variable | feature | eta^2 | variable's share |",
        "| --- | --- | --- | --- |",
    ]
    for row in result.location.table[:6]:
        lines.append(
            f"| {row['variable']} | {row['feature']} | {row['eta2']:.2f} | {row['share']:.0%} |"
        )
    lines += [
        "",
        "![locate](plots/locate.png)",
        "",
        "## Candidates",
        "",
        "Every candidate effect, fitted (with the effects already selected) on the "
        "identification episodes, judged on the held-out ones:",
        "",
        "| round | effect | target | fitted | held-out error |",
        "| --- | --- | --- | --- | --- |",
    ]
    for r in result.candidates:
        if not r["new"]:
            continue
        fitted = ", ".join(f"{k} = {_fmt(v)}" for k, v in r["params"].items())
        lines.append(
            f"| {r['round']} | {r['name']} | {r['target']} | {fitted} | {r['heldout_error']:.4g} |"
        )
    lines += ["", f"(The simulator as it is: {result.selection.states[0].heldout_error:.4g}.)", ""]
    if "candidates" in files:
        lines += ["![candidates](plots/candidates.png)", ""]
    rel = config_path.relative_to(out_dir) if config_path.is_relative_to(out_dir) else config_path
    lines += [
        "## The corrected model",
        "",
        f"- config: `{rel}`; train on it, from this report's directory, with "
        f"`python -m hds.run --config-dir {rel.parent.parent} "
        f"env={config_path.stem}`",
        f"- MJCF with the MuJoCo-native equivalents: `{mjcf_path.name}`",
        "",
    ]
    if retrain:
        lines += [
            "## Sim2real gap of PODS before and after",
            "",
            "| trained on | return on its simulator | return on the plant | gap |",
            "| --- | --- | --- | --- |",
        ]
        for r in retrain["rows"]:
            lines.append(
                f"| {r['method']} | {r['sim_return']:.1f} | {r['real_return']:.1f} | "
                f"{r['gap']:.1f} |"
            )
        lines += ["", "![gaps](plots/sim2real.png)", ""]
    t = result.timing
    lines += [
        f"Time: {t.get('total', 0.0):.1f} s (compare {t.get('compare', 0.0):.1f}, "
        f"explain {t.get('explain', 0.0):.1f})."
    ]
    return "\n".join(lines) + "\n"


def write_report(
    result: Discovery,
    env_cfg,
    out_dir,
    plot_episodes: int = 2,
    bins: int = 8,
    retrain: dict | None = None,
    data_name: str = "",
) -> dict:
    """Write every output to out_dir; returns report.json's content."""
    out_dir = Path(out_dir)
    config_path = write_config(env_cfg, result, out_dir)
    mjcf_path = write_mjcf(env_cfg, result, out_dir)
    handoff = write_handoff(env_cfg, result.missing_effects, out_dir)
    files = write_plots(result, out_dir, plot_episodes, bins)
    if retrain:
        import matplotlib.pyplot as plt

        fig = plots.gaps(retrain["rows"])
        files["sim2real"] = save_figure(fig, out_dir / "plots" / "sim2real.png")
        plt.close(fig)
    report = result.to_json()
    # paths relative to report.json's directory: a report moved or copied elsewhere still
    # finds its files (read them with `report_dir / report["corrected_config"]`)
    local = lambda path: Path(path).relative_to(out_dir).as_posix()  # noqa: E731
    report["corrected_config"] = local(config_path)
    report["corrected_mjcf"] = local(mjcf_path)
    report["sysid_handoff"] = {
        "params": local(handoff.params),
        "handed_off": handoff.handed_off,
        "not_handed_off": handoff.not_handed_off,
    }
    report["run_command"] = (  # from the report's directory
        f"python -m hds.run --config-dir {local(config_path.parent.parent)} env={config_path.stem}"
    )
    if retrain:
        report["retrain"] = retrain
    atomic_write_json(out_dir / "report.json", _finite(report))
    text = markdown(result, files, config_path, mjcf_path, out_dir, retrain, data_name)
    atomic_write_bytes(out_dir / "report.md", text.encode())
    # the same as one page that opens anywhere (figures inside): for a browser, and W&B
    page = markdown_page(text, out_dir, f"Gap discovery report: {data_name or out_dir.name}")
    atomic_write_bytes(out_dir / "report.html", page.encode())
    return report


def _finite(obj):
    """JSON has no inf: unbounded interval ends become null."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    if isinstance(obj, np.floating | np.integer):
        return obj.item()
    return obj
