"""The map side of macroloc: building models, macro-features, descriptors, registration, the pose graph.

A pure library: it never imports `service`, zenoh or the CLI.
"""
