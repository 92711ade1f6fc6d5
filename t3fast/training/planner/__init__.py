"""Training the route planner on its own, on many cached windows."""
