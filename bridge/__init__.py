"""scmbridge's I/O side, in layers (docs/ARCHITECTURE.md): ``core`` (wire, configuration, gate, clock),
``nodes`` (station, driver host, Zenoh plumbing) and ``tools`` (the CLI, the demo and the operator's tools)."""
