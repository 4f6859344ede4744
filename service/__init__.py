"""The composition root: config, CLI, Zenoh I/O, the localization session, planning, recordings; offline replay,
reports and bags in service.offline (docs/architecture.md: the rooms)."""
