"""The networks of T3Former: the triplane autoencoder (encoder, decoder), the forecasters, the planners, the
box motion network. :class:`~t3fast.models.world_model.T3Former` holds them and forecasts
(:mod:`t3fast.forecast`); it is imported from its module, not here, so that the agent machinery
(:mod:`t3fast.agents`) can read :mod:`t3fast.models.ego_motion` without importing the forecast."""

from t3fast.models.autoencoder import TriplaneAutoencoder
from t3fast.models.config import AutoencoderConfig, WorldModelConfig
from t3fast.models.decoder import TriplaneDecoder
from t3fast.models.encoder import TriplaneEncoder
from t3fast.models.forecaster import DeltaTriplaneForecaster
from t3fast.models.planner import MotionPlanner
from t3fast.models.triplane import Triplane

__all__ = [
    "AutoencoderConfig",
    "DeltaTriplaneForecaster",
    "MotionPlanner",
    "Triplane",
    "TriplaneAutoencoder",
    "TriplaneDecoder",
    "TriplaneEncoder",
    "WorldModelConfig",
]
