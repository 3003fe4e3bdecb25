"""scmbridge's I/O side: Zenoh messages and keys, the base-station service, the driver host and the CLI."""
