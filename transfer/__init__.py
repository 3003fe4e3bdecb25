"""The method of the paper, pure and deterministic: SC maps, command pairs, learner limits, mapping regions,
the transfer policy, the teacher model and its controllers. No I/O, no threads, no clocks: time is an argument."""
