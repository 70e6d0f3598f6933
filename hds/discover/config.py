"""The primary config of `python -m hds.discover` (`conf/discover.yaml`): a measured dataset and
the run's groups (env: the simulator compared with the data; real, algo, ...: only for
`retrain=true`). The schemas live with the run's in hds.config (registered there with Hydra's
ConfigStore as `discover_schema`), since `python -m hds.run simulator=corrected` runs discovery
too and compose() needs them; they are named here too, for discovery's users.
"""

from hds.config import DiscoverAppConfig, DiscoverConfig, EmpsConfig, plant_has_effects

__all__ = ["DiscoverAppConfig", "DiscoverConfig", "EmpsConfig", "plant_has_effects"]
