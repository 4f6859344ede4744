"""The composition root: config, CLI, Zenoh I/O, the localization state machine, planning, recordings."""
