"""The sizes of the models (the named ones are in :mod:`t3fast.presets`); the defaults are the papers'."""

from __future__ import annotations

from dataclasses import dataclass, field

from t3fast.data.classes import GRID_SHAPE, NUM_CLASSES


@dataclass
class AutoencoderConfig:
    """Sizes of :class:`TriplaneEncoder` and :class:`TriplaneDecoder`.

    ``latent="triplane"`` pools the encoded volume into three planes of ``channels``
    channels; ``latent="bev"`` keeps only the xy plane (the BEV-only ablation; raise
    ``channels`` to match the triplane's latent size).
    """

    grid: tuple[int, int, int] = GRID_SHAPE
    num_classes: int = NUM_CLASSES
    latent: str = "triplane"
    embed_dim: int = 16  # class embedding width
    full_res_channels: int = 32  # width of the blocks at 200 x 200 x 16
    full_res_blocks: int = 1
    half_res_channels: int = 64  # width of the blocks after the (2, 2, 1) downsample
    half_res_blocks: int = 2
    channels: int = 8  # C: triplane channels
    decoder_channels: int = 64  # C_f: plane channels after refinement
    decoder_hidden: list[int] = field(default_factory=lambda: [256, 256, 256, 256])
    pe_freqs: int = 6
    refine: bool = True

    def __post_init__(self) -> None:
        if self.latent not in ("triplane", "bev"):
            raise ValueError(f"latent must be 'triplane' or 'bev', got {self.latent!r}")
        self.grid = tuple(self.grid)

    @property
    def plane_shape(self) -> tuple[int, int, int]:
        """(X', Y', Z') of the planes: x and y halved, z kept."""
        x, y, z = self.grid
        return (x + 1) // 2, (y + 1) // 2, z

    @property
    def latent_size(self) -> int:
        """Numbers in one frame's latent: C X'Y' (BEV) or C (X'Y' + X'Z' + Y'Z') (triplane)."""
        x, y, z = self.plane_shape
        return self.channels * (x * y if self.latent == "bev" else x * y + x * z + y * z)


@dataclass
class WorldModelConfig:
    """Sizes of the forecaster and the planner (the autoencoder has its own config).

    ``scales`` takes the first ``scales`` entries of ``forecaster_widths`` (1 = the
    single-scale ablation); ``predict_delta=False`` predicts the full next plane (the
    no-Delta ablation). A BEV-only latent follows from the autoencoder's config.
    """

    forecaster_widths: list[int] = field(default_factory=lambda: [32, 48, 64, 96, 128])
    scales: int = 5
    forecaster_heads: int = 4
    forecaster_layers: int = 1
    max_tokens: int = 1024  # full attention at scales with history * h * w <= this
    history: int = 5
    steps: int = 6
    predict_delta: bool = True
    planner_widths: list[int] = field(default_factory=lambda: [64, 128, 256, 512])  # ResNet-18
    d_act: int = 50
    planner_heads: int = 5
    planner_layers: int = 2
    past_actions: int = 4
    # forecast in the present frame (history moved there with the past poses; each future
    # frame decoded in its own ego frame from its pose); False: the papers' formulation, each
    # frame in its own ego frame
    ego_aligned: bool = False
    # ego-aligned forecasts keep the present frame's observed static world (see
    # t3fast.models.world_model.observed_static); False: decoded frames only
    static_from_present: bool = True

    def __post_init__(self) -> None:
        if not 1 <= self.scales <= len(self.forecaster_widths):
            raise ValueError(f"scales must be in [1, {len(self.forecaster_widths)}], got {self.scales}")

