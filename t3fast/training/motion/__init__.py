"""Training the flow forecaster's motion head on its own, on many cached windows."""
