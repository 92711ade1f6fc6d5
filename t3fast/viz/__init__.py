"""Pictures of occupancy: bird's-eye PNG/GIF (:mod:`t3fast.viz.bev`)."""
