"""The long-running nodes: the station, the driver host and the Zenoh plumbing they share
(docs/ARCHITECTURE.md, section 2)."""
