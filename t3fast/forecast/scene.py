"""Stage 3: the scene forecast, the triplanes of the future steps (Phi_fut)."""

from __future__ import annotations

import torch

from t3fast.forecast.records import Agents, Past, Scene
from t3fast.models.flow_forecaster import FlowTriplaneForecaster
from t3fast.models.forecaster import DeltaTriplaneForecaster


class FlowScene:
    """The flow forecaster (:mod:`t3fast.models.flow_forecaster`): all steps at once from the
    history and the tracker's velocities, with the displacements it moved the present cells by."""

    def __init__(self, forecaster: FlowTriplaneForecaster):
        self.forecaster = forecaster

    @torch.no_grad()
    def __call__(self, past: Past, agents: Agents, steps: int) -> Scene:
        futures, changes, displacements = self.forecaster(past.planes, agents.velocity, steps)
        return Scene(futures, changes, displacements)


class DeltaScene:
    """The papers' Delta forecaster (:mod:`t3fast.models.forecaster`), autoregressive; it moves
    no agents explicitly (no displacements)."""

    def __init__(self, forecaster: DeltaTriplaneForecaster):
        self.forecaster = forecaster

    @torch.no_grad()
    def __call__(self, past: Past, agents: Agents, steps: int) -> Scene:
        futures, changes = self.forecaster(past.planes, steps, 0)
        return Scene(futures, changes, None)
