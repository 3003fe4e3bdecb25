"""The software learner: degraded unicycle dynamics, the paper's worlds, link emulators and experiment runners."""
