"""Gap discovery: find where the simulator and measured data disagree, name the missing
effects of the library, add them to the model, and show the gap shrink.

  compare   replay measured actions from measured states: one-step and k-step residuals
  locate    which state variables disagree, and on which features their residual depends
  explain   every candidate effect fitted through the differentiable simulator (batched
            Levenberg-Marquardt on k-step errors, delays enumerated); greedy forward
            selection on held-out error
  name      physical names, parameters with units and 95% CIs, explained and unexplained shares
  add/show  corrected env config and MJCF, report.md / report.json / plots

Python API:

    from hds.discover import discover, write_report, DiscoverConfig
    result = discover(dataset, env_cfg, DiscoverConfig(horizon=10))   # a Discovery
    result.missing_effects        # [NamedEffect(name, target, params, units, ci95, ...)]
    write_report(result, env_cfg, "out/")

Command line: python -m hds.discover data=PATH [env=...] [retrain=true] (conf/discover.yaml).
"""

from hds.discover.config import DiscoverAppConfig, DiscoverConfig
from hds.discover.identify import Identifiability, identifiability, record_until_identifiable
from hds.discover.io import load_dataset
from hds.discover.workflow import Discovery, NamedEffect, Result, discover
from hds.discover.write import corrected_env, write_report

__all__ = [
    "DiscoverAppConfig",
    "DiscoverConfig",
    "Discovery",
    "Identifiability",
    "NamedEffect",
    "Result",
    "corrected_env",
    "discover",
    "identifiability",
    "load_dataset",
    "record_until_identifiable",
    "write_report",
]
