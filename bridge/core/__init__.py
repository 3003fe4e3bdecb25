"""The small core every other layer builds on: the wire contract, the configuration schema, the driver host's
pure safety gate and the clock helpers. No Zenoh, no threads, no vehicle link (docs/ARCHITECTURE.md, section 2)."""
