"""Teacher side: the unicycle model and the controllers/planners that drive it (motion primitives, MPC)."""
