"""The sizes of the models (the named ones are in :mod:`t3fast.presets`); the defaults are the papers'.

Each config checks its values when built (also from a checkpoint's or a file's config): a
:class:`~t3fast.errors.ConfigError` names the key, the value and the allowed range, so a bad
size is refused before any model is built from it. The ranges are wide (no width above
:data:`MAX_WIDTH`, no depth above :data:`MAX_DEPTH`); how many parameters a config builds is
checked where a checkpoint becomes a model (:mod:`t3fast.pretrained`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from t3fast.data.classes import GRID_SHAPE, NUM_CLASSES
from t3fast.errors import ConfigError

#: largest channel count, hidden width, grid side or sequence length a config may ask for
MAX_WIDTH = 1 << 16
#: largest number of blocks, layers or hidden layers of one stack
MAX_DEPTH = 32
#: largest pe_freqs the fused decode op accepts
MAX_PE_FREQS = 30


def check_int(key: str, value: Any, low: int, high: int = MAX_WIDTH) -> None:
    """Raises :class:`ConfigError` unless ``value`` is an integer in ``[low, high]``."""
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ConfigError(f"'{key}' must be an integer in [{low}, {high}], got {value!r}")


def check_ints(key: str, values: Any, low: int, min_len: int = 0) -> None:
    """A list of at most :data:`MAX_DEPTH` integers, each in ``[low, MAX_WIDTH]``."""
    if not isinstance(values, list | tuple) or not min_len <= len(values) <= MAX_DEPTH:
        raise ConfigError(f"'{key}' must be a list of {min_len} to {MAX_DEPTH} integers, got {values!r}")
    for i, value in enumerate(values):
        check_int(f"{key}[{i}]", value, low)


def check_group_norm_width(key: str, width: int) -> None:
    """The blocks normalise with ``min(8, width)`` groups, which must divide ``width``."""
    if width > 8 and width % 8:
        raise ConfigError(f"'{key}' must be a multiple of 8 (or at most 8) for the group norm, got {width}")


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
            raise ConfigError(f"'latent' must be 'triplane' or 'bev', got {self.latent!r}")
        if not isinstance(self.grid, list | tuple) or len(self.grid) != 3:
            raise ConfigError(f"'grid' must be the 3 sides (X, Y, Z) of the voxel grid, got {self.grid!r}")
        self.grid = tuple(self.grid)
        for axis, side in zip("XYZ", self.grid):
            check_int(f"grid ({axis})", side, 1)
        check_int("num_classes", self.num_classes, 1, 256)  # argmax labels are uint8
        for key in ("embed_dim", "full_res_channels", "half_res_channels", "channels", "decoder_channels"):
            check_int(key, getattr(self, key), 1)
        for key in ("full_res_blocks", "half_res_blocks"):
            check_int(key, getattr(self, key), 0, MAX_DEPTH)
        for key in ("full_res_channels", "half_res_channels"):
            check_group_norm_width(key, getattr(self, key))
        check_ints("decoder_hidden", self.decoder_hidden, 1)
        check_int("pe_freqs", self.pe_freqs, 0, MAX_PE_FREQS)
        if not isinstance(self.refine, bool):
            raise ConfigError(f"'refine' must be true or false, got {self.refine!r}")
        if not self.refine and self.decoder_channels != self.channels:
            raise ConfigError(f"'decoder_channels' ({self.decoder_channels}) must equal 'channels' "
                              f"({self.channels}) when 'refine' is false")

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


#: keys of earlier versions that :meth:`WorldModelConfig.upgrade` drops
REMOVED_FLOW_SWITCHES = ("tracker_prior", "motion_context")


@dataclass
class WorldModelConfig:
    """Sizes of the forecaster and the planner (the autoencoder has its own config).

    ``scales`` takes the first ``scales`` entries of ``forecaster_widths`` (1 = the
    single-scale ablation); ``predict_delta=False`` predicts the full next plane (the
    no-Delta ablation). A BEV-only latent follows from the autoencoder's config.
    """

    # "delta": the papers' DeltaTriplaneForecaster (attention per scale, autoregressive);
    # "flow": FlowTriplaneForecaster (the present xy plane moved by a predicted flow, plus Delta)
    forecaster: str = "delta"
    forecaster_widths: list[int] = field(default_factory=lambda: [32, 48, 64, 96, 128])
    scales: int = 5
    forecaster_heads: int = 4
    forecaster_layers: int = 1
    max_tokens: int = 1024  # full attention at scales with history * h * w <= this
    flow_widths: list[int] = field(default_factory=lambda: [16, 32, 48, 64, 96])  # the flow forecaster's UNet
    flow_scale: float = 2.0  # plane cells per unit of the velocities and corrections its networks read and predict
    match_radius: int = 6  # its matching costs look this many plane cells around each cell
    # draw the observed agents moved along the flow forecaster's displacements (label space)
    # instead of decoding them from the forecast latent (see T3Former._render_agents)
    render_agents: bool = False
    # draw those agents as the boxes fitted to their columns in the past frames, moved by the same
    # displacement without rounding it to cells (t3fast.agents.boxes)
    agent_boxes: bool = False
    # move those boxes by a learned network of their kinematics and the scene around them
    # (t3fast.models.box_motion, t3fast.agents.box_kinematics) instead of the forecaster's displacement
    box_motion: bool = False
    history: int = 5
    steps: int = 6
    predict_delta: bool = True
    # "phi_act": the papers' MotionPlanner (reads the forecast triplanes); "route": RoutePlanner
    # (the road ahead in the present plane, the past motion and the route command)
    planner: str = "phi_act"
    # the route planner reads the road ahead (a CNN over the present plane and its change); False:
    # the past motion and the route command only
    route_scene: bool = True
    route_modes: int = 1  # candidate plans of the route planner (the best-scored one is the plan)
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

    @staticmethod
    def upgrade(raw: dict) -> dict:
        """A config of an earlier version (a checkpoint's, or overrides) in this version's keys.
        ``tracker_prior`` and ``motion_context`` switched the flow forecaster's tracker prior and
        the scene its motion head reads; the flow forecaster now always has both, so the keys
        are dropped, and switching either off for it is refused."""
        raw = dict(raw)
        for key in REMOVED_FLOW_SWITCHES:
            if key in raw and str(raw.pop(key)).strip().lower() in ("false", "0", "no", "off") and \
                    raw.get("forecaster") == "flow":
                raise ConfigError(f"'{key}=false' is no longer supported: the flow forecaster always starts from the "
                                  "tracker's velocities and corrects them with a head that reads the scene")
        return raw

    def __post_init__(self) -> None:
        if self.forecaster not in ("delta", "flow"):
            raise ConfigError(f"'forecaster' must be 'delta' or 'flow', got {self.forecaster!r}")
        if self.planner not in ("phi_act", "route"):
            raise ConfigError(f"'planner' must be 'phi_act' or 'route', got {self.planner!r}")
        if self.planner == "route" and not self.ego_aligned:
            raise ConfigError("'planner'='route' reads the road ahead in the ego-aligned present plane: it needs "
                              "ego_aligned=true")
        check_int("route_modes", self.route_modes, 1, 16)
        check_ints("flow_widths", self.flow_widths, 1, min_len=1)
        for i, width in enumerate(self.flow_widths):
            check_group_norm_width(f"flow_widths[{i}]", width)
        if not (isinstance(self.flow_scale, int | float) and 0 < self.flow_scale < 1e3):
            raise ConfigError(f"'flow_scale' must be a number in (0, 1000), got {self.flow_scale!r}")
        radius = self.match_radius
        if isinstance(radius, bool) or not (isinstance(radius, int) and 0 <= radius <= 16):
            raise ConfigError(f"'match_radius' must be an integer in [0, 16], got {self.match_radius!r}")
        if not 1 <= self.scales <= len(self.forecaster_widths):
            raise ValueError(f"scales must be in [1, {len(self.forecaster_widths)}], got {self.scales}")
        check_ints("forecaster_widths", self.forecaster_widths, 1, min_len=1)
        check_int("scales", self.scales, 1, len(self.forecaster_widths))
        check_int("forecaster_heads", self.forecaster_heads, 1)
        for i, width in enumerate(self.forecaster_widths[: self.scales]):
            check_group_norm_width(f"forecaster_widths[{i}]", width)
            if width % self.forecaster_heads:
                raise ConfigError(f"'forecaster_heads' ({self.forecaster_heads}) must divide every width of "
                                  f"'forecaster_widths', but not forecaster_widths[{i}] = {width}")
        check_int("forecaster_layers", self.forecaster_layers, 1, MAX_DEPTH)
        check_int("max_tokens", self.max_tokens, 0, 1 << 31)
        check_int("history", self.history, 2)  # motion needs two frames (the local attention reads the last two)
        check_int("steps", self.steps, 1)
        check_ints("planner_widths", self.planner_widths, 1, min_len=1)
        for i, width in enumerate(self.planner_widths):
            check_group_norm_width(f"planner_widths[{i}]", width)
        check_int("d_act", self.d_act, 1)
        check_int("planner_heads", self.planner_heads, 1)
        if self.d_act % self.planner_heads:
            raise ConfigError(f"'planner_heads' ({self.planner_heads}) must divide 'd_act' ({self.d_act})")
        check_int("planner_layers", self.planner_layers, 1, MAX_DEPTH)
        check_int("past_actions", self.past_actions, 1)
        if self.render_agents is True and self.forecaster != "flow":
            raise ConfigError("'render_agents' draws agents along the flow forecaster's displacements: it needs "
                              f"forecaster='flow', got {self.forecaster!r}")
        if self.agent_boxes is True and self.render_agents is not True:
            raise ConfigError("'agent_boxes' draws the agents 'render_agents' moves as fitted boxes: it needs "
                              "render_agents=true")
        if self.box_motion is True and self.agent_boxes is not True:
            raise ConfigError("'box_motion' moves the fitted boxes 'agent_boxes' draws: it needs agent_boxes=true")
        for key in ("predict_delta", "ego_aligned", "static_from_present", "render_agents", "agent_boxes",
                    "box_motion"):
            if not isinstance(getattr(self, key), bool):
                raise ConfigError(f"'{key}' must be true or false, got {getattr(self, key)!r}")

