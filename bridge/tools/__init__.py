"""What a person runs: the ``scmbridge`` CLI, the demo and the operator's tools (docs/ARCHITECTURE.md, section 2)."""
