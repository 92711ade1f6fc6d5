"""Models of T3Former: the triplane autoencoder (encoder, decoder), the forecaster, the planner."""

from t3fast.models.autoencoder import TriplaneAutoencoder
from t3fast.models.config import AutoencoderConfig, WorldModelConfig
from t3fast.models.decoder import TriplaneDecoder
from t3fast.models.encoder import TriplaneEncoder
from t3fast.models.forecaster import DeltaTriplaneForecaster
from t3fast.models.planner import MotionPlanner
from t3fast.models.triplane import Triplane
from t3fast.models.world_model import Forecast, T3Former

__all__ = [
    "T3Former",
    "AutoencoderConfig",
    "DeltaTriplaneForecaster",
    "Forecast",
    "MotionPlanner",
    "Triplane",
    "TriplaneAutoencoder",
    "TriplaneDecoder",
    "TriplaneEncoder",
    "WorldModelConfig",
]
