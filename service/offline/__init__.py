"""Offline: replaying a recording or a ROS 2 bag through the service's localization session, its reports and
plots, recordings as Foxglove files and bags. It may import the service's runtime modules (`service.localizer_loop`,
`service.recording`, `service.config`, ...); they never import it (tests/graph/test_layering.py)."""
