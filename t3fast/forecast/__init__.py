"""The forecast as a pipeline of stages, each with one job and typed inputs and outputs.

:class:`~t3fast.models.world_model.T3Former` holds the networks; :mod:`t3fast.forecast.pipeline`
picks the stages once from its config and runs them in order:

1. :mod:`~t3fast.forecast.encode`: the past frames (and the present) into triplanes, in the
   present ego frame (ego-aligned) or each in its own -> :class:`~t3fast.forecast.records.Past`;
2. :mod:`~t3fast.forecast.agents`: the present's agents, tracked and boxed by the classical
   tracker (:mod:`t3fast.agents`) -> :class:`~t3fast.forecast.records.Agents`;
3. :mod:`~t3fast.forecast.scene`: the triplane forecaster -> :class:`~t3fast.forecast.records.Scene`;
4. :mod:`~t3fast.forecast.motion`: where each agent goes (the box motion network, else the
   forecaster's tracker-prior motion) -> :class:`~t3fast.forecast.records.AgentMoves`;
5. :mod:`~t3fast.forecast.plan`: the ego's future displacements and poses (route planner or
   Phi_act, or the given ones) -> :class:`~t3fast.forecast.records.Plan`;
6. :mod:`~t3fast.forecast.render`: the future frames as labels, each in the ego frame of its pose.
"""
