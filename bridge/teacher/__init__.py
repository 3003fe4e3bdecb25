"""The teacher's runtime beside its method (``transfer/teacher/``): what running the MPC on a machine needs that the
pure method must not do itself, i.e. its CasADi functions generated as C, compiled once per machine and cached
(:mod:`bridge.teacher.codegen`). Layer 1 of docs/ARCHITECTURE.md: it imports the method and ``bridge.core`` only."""
