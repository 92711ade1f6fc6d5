"""The classical agent machinery: no learned weights, only geometry and matching.

* :mod:`t3fast.agents.tracker`: the agents of a frame (BEV components of vehicle and human
  columns), their matches in earlier frames and their velocities;
* :mod:`t3fast.agents.boxes`: boxes fitted to each agent's columns in every observed frame, and
  drawn into a label volume;
* :mod:`t3fast.agents.box_kinematics`: a fitted box's kinematics and view of the scene (what the
  box motion network reads) and its constant-velocity motion (the prior that network corrects).
"""
