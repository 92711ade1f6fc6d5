"""Training the fitted boxes' motion network (:mod:`t3fast.models.box_motion`)."""
