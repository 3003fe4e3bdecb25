"""``scmbridge bench fuzz``, cut by job: :mod:`bench.fuzz.main` (the command: inputs, JSON), :mod:`~bench.fuzz.harness`
(what every input shares), :mod:`~bench.fuzz.messages` (MessagePack mutations), :mod:`~bench.fuzz.host` (Zenoh into a
driver host), :mod:`~bench.fuzz.rss` (the RSS study), and one module per link: ``udp_link``, ``can_frames`` /
``can_link``, ``mavlink_frames`` / ``mavlink_link``."""
